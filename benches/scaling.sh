#!/usr/bin/env bash
# Strong scaling (issue 40, docs/benchmarks.md "Where data lives: auto, and strong
# scaling"): the same job on a
# `dray cluster --threads 1` of 1, 2, 3 workers, against `dray render --threads 1` in one
# process, on a scene that fits every worker's budget (auto: replicated) and on one that
# does not (auto: dynamic over owned domains). RUNS jobs per cluster; the median of each
# is printed, with the speed-up over one worker and the ratio to one process.
#
#   benches/scaling.sh
#   DRAY_BIN=target/release/dray RUNS=3 WORKERS="1 2 3" benches/scaling.sh
#   FIT="cornell:glass --width 320 --height 240 --spp 64" benches/scaling.sh
#   SCHEDULE=image-plane benches/scaling.sh    # force a schedule instead of auto
#   CASES=big BIG_BUDGET=40000000 benches/scaling.sh   # in between: auto copies hot
#                                  # domains (SCHEDULE=dynamic: the same without copies)
#
# Builds dray (cargo build --release -p dray) unless DRAY_BIN is set. Times are the
# wall time of the command that waits for the image (`dray submit` against a running
# cluster: scene load, package, tracing, image; `dray render`: the same in one process),
# so a cluster pays for everything it does beyond one process. Every image of a case
# is compared with the first (same bits). Output: one line per (case, workers).
set -euo pipefail
cd "$(dirname "$0")/.."
if [[ -z "${DRAY_BIN:-}" ]]; then
    cargo build --release -p dray >&2
    DRAY_BIN=${CARGO_TARGET_DIR:-target}/release/dray
fi
RUNS=${RUNS:-3}
WORKERS=${WORKERS:-1 2 3}
SCHEDULE=${SCHEDULE:-auto}
CASES=${CASES:-fit big}
# Fits: 1.1 MB resident, no budget. Does not fit: 16 kd domains of about 2.6 MB against
# a budget that holds two (the regression guard's scene and budget).
FIT=${FIT:-spheres:64 --width 640 --height 480 --spp 64}
BIG=${BIG:-grid:iso:gyroid:48:2x2x2 --domains 16 --width 320 --height 240 --spp 8 --max-depth 2}
BIG_BUDGET=${BIG_BUDGET:-12000000}
OUT=$(mktemp -d)
CLUSTER=
cleanup() {
    if [[ -n "$CLUSTER" ]]; then
        kill "$CLUSTER" 2>/dev/null || true
        wait "$CLUSTER" 2>/dev/null || true
    fi
    rm -rf "$OUT"
}
trap cleanup EXIT

# Seconds of wall time of "$@", to stdout; the command's own output to $OUT/last.err.
timed() {
    local t0 t1
    t0=$(date +%s.%N)
    "$@" >/dev/null 2>"$OUT/last.err" || { cat "$OUT/last.err" >&2; return 1; }
    t1=$(date +%s.%N)
    python3 -c "print(f'{$t1 - $t0:.3f}')"
}

median() { python3 -c 'import statistics,sys; print(f"{statistics.median(map(float, sys.argv[1:])):.3f}")' "$@"; }

start_cluster() { # workers, budget
    "$DRAY_BIN" cluster --workers "$1" --threads 1 --base-port 0 --memory-budget "$2" \
        --work-dir "$OUT/work-$1-$2" >"$OUT/cluster.out" 2>"$OUT/cluster.err" &
    CLUSTER=$!
    for _ in $(seq 1 600); do
        grep -q ready "$OUT/cluster.out" 2>/dev/null && break
        kill -0 "$CLUSTER" 2>/dev/null || break
        sleep 0.2
    done
    if ! grep -q ready "$OUT/cluster.out"; then
        echo "dray cluster --workers $1 did not become ready:" >&2
        cat "$OUT/cluster.out" "$OUT/cluster.err" >&2
        exit 1
    fi
    ADDR=$(grep -o '127.0.0.1:[0-9]*' "$OUT/cluster.out" | head -1)
}

stop_cluster() {
    kill "$CLUSTER" 2>/dev/null || true
    wait "$CLUSTER" 2>/dev/null || true
    CLUSTER=
}

echo "# $(date -u +%FT%TZ) $(nproc) cores, load average $(cut -d' ' -f1-3 /proc/loadavg)"
echo "case workers median_s runs speedup_vs_1 ratio_vs_one_process schedule bytes_between_processes domain_loads rays_exchanged"
for case in $CASES; do
    if [[ $case == fit ]]; then read -ra JOB <<<"$FIT"; budget=0; else read -ra JOB <<<"$BIG"; budget=$BIG_BUDGET; fi
    # One process, one tracing thread (the reference renderer, then the default
    # in-process actors with one worker).
    one=()
    for r in $(seq 1 "$RUNS"); do
        one+=("$(timed "$DRAY_BIN" render "${JOB[@]}" --threads 1 --workers 0 -q \
            --memory-budget "$budget" --output "$OUT/$case-ref.png")")
    done
    base=$(median "${one[@]}")
    echo "$case one-process $base ${one[*]// /,} - 1.00 none 0 0 0"
    t1=
    for n in $WORKERS; do
        start_cluster "$n" "$budget"
        runs=()
        for r in $(seq 1 "$RUNS"); do
            tag="$case-$n-$r"
            runs+=("$(timed "$DRAY_BIN" submit "${JOB[@]}" --schedule "$SCHEDULE" --passes one \
                --coordinator "http://$ADDR" --stats "$OUT/$tag.json" --output "$OUT/$tag.png")")
            cmp -s "$OUT/$case-ref.png" "$OUT/$tag.png" ||
                echo "  $tag: image differs from one process's" >&2
        done
        stop_cluster
        m=$(median "${runs[@]}")
        [[ -z "$t1" ]] && t1=$m
        # Counts of the first run, the cluster's cold one (later runs find the
        # package's domains warm: loads fall to the few evicted ones); loads and rays
        # moved depend less on the machine's speed than times do. "+copies" when auto
        # turned on hot-domain replication (its reason says so).
        read -r sched bytes loads moved < <(python3 - "$OUT/$case-$n-1.json" <<'PY'
import json, sys
d = json.load(open(sys.argv[1]))
s = d.get("scheduling", d)
name = s.get("schedule", "?")
if "hot-domain replication" in s.get("placement", "") or "--replicate" in s.get("placement", ""):
    name += "+copies"
print(name, s.get("traffic", {}).get("total", 0), s.get("domain_loads", 0), s.get("rays_exchanged", 0))
PY
)
        python3 -c "import sys; t1,m,b=map(float,sys.argv[1:4]); print(sys.argv[4], sys.argv[5], f'{m:.3f}', sys.argv[6], f'{t1/m:.2f}', f'{m/b:.2f}', *sys.argv[7:])" \
            "$t1" "$m" "$base" "$case" "$n" "$(IFS=,; echo "${runs[*]}")" "$sched" "$bytes" "$loads" "$moved"
    done
done
