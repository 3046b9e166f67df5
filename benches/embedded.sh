#!/usr/bin/env bash
# What the embedded mode's actors cost: `dray render` (coordinator + 1 worker actor in one
# process, the default) against the reference renderer (`--workers 0`, no actors), on
# the same scenes and settings. Prints, per scene, the median wall time of each over
# RUNS runs (default 3), their ratio, the peak RSS of each, and whether the PNGs are
# bit-identical.
# Usage: benches/embedded.sh            (DRAY_BIN=path skips the build; RUNS=n)
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."
if [ -z "${DRAY_BIN:-}" ]; then
    cargo build --release -p dray
    DRAY_BIN=target/release/dray
fi
RUNS="${RUNS:-3}"
out=$(mktemp -d)
trap 'rm -rf "$out"' EXIT

# scene | flags
cases=(
  "cornell|--spp 16"
  "cornell:glass|--spp 16 --max-depth 8"
  "spheres:200|--spp 16"
  "city:8|--integrator ao --spp 4"
  "grid:spheres:200:3x3x3|--spp 1 --width 320 --height 240"
)
# The deep scanned-model case (Lucy, path tracing to depth 64; docs/benchmarks.md, "Path
# tracing against Mitsuba 3"), when benches/vs_mitsuba.sh --case deep has written its
# scene; at 1 and 2 threads.
deep="${DEEP_SCENE:-benches/out/vs_mitsuba_deep/scene.gltf}"
if [ -f "$deep" ]; then
  for t in 1 2; do
    cases+=("$deep|--width 256 --height 256 --spp 64 --integrator path --max-depth 64 --env 0.25,0.25,0.25 --threads $t")
  done
else
  echo "note: $deep not found (run benches/vs_mitsuba.sh --case deep to make it); the deep case is skipped" >&2
fi

median() { sort -g | awk '{a[NR]=$1} END {print a[int((NR+1)/2)]}'; }

# run MODE SCENE FLAGS...: prints "seconds peak_kb" of one render
run() {
  local mode=$1 scene=$2; shift 2
  local extra=()
  [ "$mode" = reference ] && extra=(--workers 0)
  /usr/bin/time -f "%e %M" -o "$out/time" "$DRAY_BIN" render "$scene" "$@" "${extra[@]}" \
      -q --output "$out/$mode.png" >/dev/null
  cat "$out/time"
}

printf "%-26s %-34s %10s %10s %7s %10s %10s %s\n" scene flags "ref s" "actors s" ratio "ref MB" "actors MB" bits
for c in "${cases[@]}"; do
  scene=${c%%|*}; flags=${c#*|}
  declare -A t=() m=()
  : >"$out/reference.times"
  : >"$out/actors.times"
  # Interleaved, so that any other load on the machine hits both alike.
  for _ in $(seq "$RUNS"); do
    for mode in reference actors; do
      # shellcheck disable=SC2086
      run "$mode" "$scene" $flags >>"$out/$mode.times"
    done
  done
  for mode in reference actors; do
    t[$mode]=$(cut -d' ' -f1 "$out/$mode.times" | median)
    m[$mode]=$(cut -d' ' -f2 "$out/$mode.times" | sort -g | tail -1)
  done
  same=$(cmp -s "$out/reference.png" "$out/actors.png" && echo same || echo DIFFER)
  printf "%-26s %-34s %10s %10s %7.2f %10d %10d %s\n" "$scene" "$flags" "${t[reference]}" "${t[actors]}" \
    "$(echo "${t[actors]} / ${t[reference]}" | bc -l)" $(( ${m[reference]} / 1024 )) $(( ${m[actors]} / 1024 )) "$same"
done
