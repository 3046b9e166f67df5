#!/usr/bin/env bash
# Many workers on one machine: a job on `dray cluster --workers 64 --threads 1` with small
# memory budgets (out of core, the dynamic schedule), checked bit for bit against
# `dray render` of the same job. Prints one JSON line: workers, wall time of the job,
# peak RSS of the coordinator and the largest and summed peak RSS of the workers, the
# job's domain loads, rounds and routing version, and whether the EXRs are identical.
# Results and commands: docs/benchmarks.md "Coordinator scaling".
#
# Usage: benches/cluster64.sh [WORKERS] [SCENE] [BUDGET]
#   defaults: 64, iso:gyroid:160 (about 1.2M triangles), 24M per worker.
# Takes a few minutes on 2 cores; not part of CI. Set DRAY_BIN to use a built binary.
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."
WORKERS=${1:-64}
SCENE=${2:-iso:gyroid:160}
BUDGET=${3:-24M}
FLAGS=(--width 256 --height 256 --spp 4 --integrator path --max-depth 3)
if [ -z "${DRAY_BIN:-}" ]; then
    cargo build --release -p dray
    DRAY_BIN=target/release/dray
fi
OUT=benches/out/cluster64
rm -rf "$OUT"
mkdir -p "$OUT"

"$DRAY_BIN" render "$SCENE" "${FLAGS[@]}" --exr "$OUT/render.exr" >"$OUT/render.log" 2>&1

"$DRAY_BIN" cluster --workers "$WORKERS" --threads 1 --memory-budget "$BUDGET" \
    --base-port 0 --work-dir "$OUT/work" >"$OUT/cluster.out" 2>"$OUT/cluster.log" &
CLUSTER=$!
trap 'kill -TERM $CLUSTER 2>/dev/null || true; wait $CLUSTER 2>/dev/null || true' EXIT
for _ in $(seq 1 600); do
    grep -q "^dray cluster ready" "$OUT/cluster.out" 2>/dev/null && break
    kill -0 $CLUSTER 2>/dev/null || { cat "$OUT/cluster.log" >&2; exit 1; }
    sleep 0.5
done
grep -q "^dray cluster ready" "$OUT/cluster.out" || { echo "cluster not ready" >&2; exit 1; }
ADDR=$(awk '/^coordinator/ {print $2; exit}' "$OUT/cluster.out")

start=$(date +%s.%N)
"$DRAY_BIN" submit --coordinator "$ADDR" "$SCENE" "${FLAGS[@]}" --exr "$OUT/cluster.exr" --output "$OUT/cluster.png" \
    --stats "$OUT/stats.json" >"$OUT/submit.log" 2>&1
end=$(date +%s.%N)

same=false
cmp -s "$OUT/render.exr" "$OUT/cluster.exr" && same=true
# Peak RSS (VmHWM) of every member is read while they still run.
python3 - "$OUT/stats.json" "$OUT/cluster.out" "$WORKERS" "$SCENE" "$BUDGET" "$start" "$end" "$same" <<'EOF'
import json, re, sys
stats_path, members, workers, scene, budget, start, end, same = sys.argv[1:]
def hwm_kb(pid):
    try:
        for line in open(f"/proc/{pid}/status"):
            if line.startswith("VmHWM:"):
                return int(line.split()[1])
    except OSError:
        pass
    return 0
coord, ws = 0, []
for line in open(members):
    m = re.match(r"(coordinator|worker \d+)\s+\S+\s+pid (\d+)", line)
    if m:
        kb = hwm_kb(int(m.group(2)))
        if m.group(1) == "coordinator":
            coord = kb
        else:
            ws.append(kb)
wmax, wsum = max(ws, default=0), sum(ws)
s = json.load(open(stats_path))
st = s.get("stats", s)
def g(*k):
    for key in k:
        if key in st:
            return st[key]
    return None
print(json.dumps({
    "workers": int(workers), "scene": scene, "budget": budget,
    "wall_s": round(float(end) - float(start), 2),
    "coordinator_peak_rss_mb": round(int(coord) / 1024, 1),
    "worker_peak_rss_mb_max": round(int(wmax) / 1024, 1),
    "worker_peak_rss_mb_sum": round(int(wsum) / 1024, 1),
    "domains": g("domains"), "triangles": g("triangles"),
    "domain_loads": g("domain_loads", "domainLoads"),
    "scheduler_rounds": g("scheduler_rounds", "schedulerRounds"),
    "routing_version": g("routing_version", "routingVersion"),
    "same_bits_as_dray_render": same == "true",
}))
EOF
