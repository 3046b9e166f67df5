#!/usr/bin/env bash
# Instructions per ray of `dray bench-rays` under valgrind's callgrind (instruction counts
# do not move with machine noise), and nodes and triangles tested per ray (`--count`).
#
# Usage: benches/profile_rays.sh [MESH ...]
#   default meshes: iso:gyroid:259 and the 13-copy Lucy grid (as benches/ray_throughput.sh)
#   env: DRAY_BIN (default: build and use target/release/dray), RAYS (incoherent rays,
#        default 100000), RES (primary rays RES x RES, default 256), OUT (default
#        benches/out/profile_rays), KINDS (default "primary incoherent"), COUNT (1: also
#        run --count, needs a dray with that flag; default 1), REUSE (1: reuse the callgrind
#        outputs already in OUT).
# Prints one line per mesh and kind: instructions per ray inside Accel::closest (callgrind
# collects only inside it: --toggle-collect), and nodes/triangles per ray. The per-function
# table of each run (self cost by source file, inlined code included) is kept beside the
# callgrind output as .txt.
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."
if [ -z "${DRAY_BIN:-}" ]; then
    cargo build --release -p dray
    DRAY_BIN=target/release/dray
fi
SCENES="${DRAY_SCENES:-../shared/scenes}"
RAYS="${RAYS:-100000}"
RES="${RES:-256}"
OUT="${OUT:-benches/out/profile_rays}"
KINDS="${KINDS:-primary incoherent}"
COUNT="${COUNT:-1}"
mkdir -p "$OUT"
if [ "$#" -eq 0 ]; then
    set -- "iso:gyroid:259" "grid:$SCENES/lucy_100k/lucy.ply:1x13x1"
fi
echo "| mesh | kind | rays | hits | instructions per ray (inside Accel::closest) | nodes per ray | triangles per ray |"
echo "|---|---|---:|---:|---:|---:|---:|"
for mesh in "$@"; do
    tag=$(echo "$mesh" | sed 's/[^A-Za-z0-9]\+/_/g' | tail -c 60)
    for kind in $KINDS; do
        cg="$OUT/callgrind.$tag.$kind"
        if [ -n "${REUSE:-}" ] && [ -s "$cg.json" ]; then
            json=$(cat "$cg.json")
        else
            json=$(valgrind --tool=callgrind --callgrind-out-file="$cg" \
                --collect-atstart=no --toggle-collect='*Accel::closest*' "$DRAY_BIN" bench-rays "$mesh" \
                --kind "$kind" --threads 1 --repeat 1 --rays "$RAYS" --res "$RES" 2>/dev/null | tail -n 1)
            echo "$json" > "$cg.json"
        fi
        # Keep the per-function table (self cost, by source file of the inlined code).
        callgrind_annotate "$cg" > "$cg.txt" 2>/dev/null || true
        rays=$(echo "$json" | python3 -c 'import json,sys; print(json.load(sys.stdin)["rays"])')
        hits=$(echo "$json" | python3 -c 'import json,sys; print(json.load(sys.stdin)["hits"])')
        # Only the queries are collected (--toggle-collect), so the total is theirs.
        ir=$(callgrind_annotate "$cg" 2>/dev/null | grep 'PROGRAM TOTALS' | awk '{gsub(",", "", $1); print $1}')
        per=$(python3 -c "print(f'{$ir / $rays:,.0f}')")
        nodes="-"
        tris="-"
        if [ "$COUNT" = 1 ]; then
            cj=$("$DRAY_BIN" bench-rays "$mesh" --kind "$kind" --threads 1 --repeat 1 --rays "$RAYS" \
                --res "$RES" --count | tail -n 1)
            nodes=$(echo "$cj" | python3 -c 'import json,sys; print("%.2f" % json.load(sys.stdin)["nodes_per_ray"])')
            tris=$(echo "$cj" | python3 -c 'import json,sys; print("%.2f" % json.load(sys.stdin)["triangles_per_ray"])')
        fi
        echo "| \`$mesh\` | $kind | $rays | $hits | $per | $nodes | $tris |"
    done
done
