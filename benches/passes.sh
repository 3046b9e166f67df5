#!/usr/bin/env bash
# Domain loads, evictions and job time of progressive passes under a memory budget
# (issue 38, docs/benchmarks.md "Progressive passes"): one 4-worker
# `dray cluster --memory-budget 80000000`, then `dray submit` of the same job with each
# schedule and pass cut, RUNS times each, one line per job.
#
#   DRAY_BIN=benches/out/dray-snapshot RUNS=3 benches/passes.sh
#   SCHEDULES="dynamic" PASSES="one doubling" benches/passes.sh
#
# Builds dray (cargo build --release -p dray) unless DRAY_BIN is set. Output: one line
# per job, "schedule passes run loads evictions job_s", and the images are compared
# with the first one of the same schedule (same bits, whatever the passes).
set -euo pipefail
cd "$(dirname "$0")/.."
if [[ -z "${DRAY_BIN:-}" ]]; then
    cargo build --release -p dray >&2
    DRAY_BIN=${CARGO_TARGET_DIR:-target}/release/dray
fi
RUNS=${RUNS:-1}
SCHEDULES=${SCHEDULES:-dynamic image-plane domain}
PASSES=${PASSES:-one doubling}
BUDGET=${BUDGET:-80000000}
JOB=(grid:iso:gyroid:120:2x2x2 --domains 32 --layout kd --width 192 --height 192 --spp 4
     --integrator path --max-depth 2)
OUT=$(mktemp -d)
"$DRAY_BIN" cluster --workers 4 --base-port 0 --memory-budget "$BUDGET" \
    --work-dir "$OUT/work" >"$OUT/cluster.out" 2>"$OUT/cluster.err" &
CLUSTER=$!
trap 'kill $CLUSTER 2>/dev/null; wait $CLUSTER 2>/dev/null; rm -rf "$OUT"' EXIT
for _ in $(seq 1 200); do
    grep -q ready "$OUT/cluster.out" 2>/dev/null && break
    sleep 0.2
done
ADDR=$(grep -o '127.0.0.1:[0-9]*' "$OUT/cluster.out" | head -1)
echo "schedule passes run loads evictions job_s"
for s in $SCHEDULES; do
    for p in $PASSES; do
        for r in $(seq 1 "$RUNS"); do
            tag="$s-$p-$r"
            "$DRAY_BIN" submit "${JOB[@]}" --schedule "$s" --passes "$p" \
                --coordinator "http://$ADDR" --stats "$OUT/$tag.json" \
                --output "$OUT/$tag.png" >/dev/null 2>"$OUT/$tag.err"
            python3 - "$OUT/$tag.json" "$s" "$p" "$r" <<'PY'
import json, sys
d = json.load(open(sys.argv[1]))
print(sys.argv[2], sys.argv[3], sys.argv[4], d["domain_loads"], d["evictions"],
      round(d["job_time_s"], 2))
PY
            first="$OUT/$s-one-1.png"
            [[ -f "$first" ]] || first="$OUT/$s-$p-1.png"
            cmp -s "$first" "$OUT/$tag.png" || echo "  $tag: image differs from $first"
        done
    done
done
