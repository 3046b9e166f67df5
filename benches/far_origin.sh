#!/usr/bin/env bash
# Rendering far from the origin against at the origin (docs/numerics.md "Far from the
# origin"): the same scene rendered with `--translate` 0, 1e3, 1e4, 1e5 and 1e6 along
# (1, 1, 1)/sqrt(3), one thread, embedded, one domain. Prints per case the median
# render seconds (the summary's render_time_s: tracing only, not loading or the BVH
# build) over RUNS runs, its ratio to the origin's, and the rays traced (far from the
# origin a scene's f32 corners round to a coarser grid, so the image, and the rays a
# path tracer spawns, differ somewhat). Builds dray unless DRAY_BIN is set.
# Usage: [DRAY_BIN=path] [RUNS=5] [SCENES="scene ..."] benches/far_origin.sh
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."
if [[ -z "${DRAY_BIN:-}" ]]; then
  CARGO_INCREMENTAL=0 cargo build --release -q -p dray
  DRAY_BIN=target/release/dray
fi
RUNS="${RUNS:-5}"
DRAY_SCENES="${DRAY_SCENES:-../shared/scenes}"
SCENES="${SCENES:-$DRAY_SCENES/stanford_bunny/bun_zipper.ply grid:spheres:20:2x2x2}"
FLAGS=(--threads 1 --width 256 --height 256 --spp 4 --integrator path --max-depth 4 -q)
out=$(mktemp -d)
trap 'rm -rf "$out"' EXIT

median() { sort -g | awk '{a[NR]=$1} END {print a[int((NR+1)/2)]}'; }
field() { python3 -c "import json,sys; print(json.load(open(sys.argv[1]))[sys.argv[2]])" "$1" "$2"; }

printf '%-44s %10s %10s %8s %12s\n' scene translate render_s ratio rays
for scene in $SCENES; do
  base=""
  for d in 0 1e3 1e4 1e5 1e6; do
    t=$(python3 -c "print(','.join([repr($d / 3 ** 0.5)] * 3))")
    : >"$out/times"
    for _ in $(seq "$RUNS"); do
      "$DRAY_BIN" render "$scene" "${FLAGS[@]}" --translate="$t" --output "$out/img.png" \
        --stats "$out/stats.json" >/dev/null 2>&1
      field "$out/stats.json" render_time_s >>"$out/times"
    done
    m=$(median <"$out/times")
    [[ -z "$base" ]] && base=$m
    rays=$(field "$out/stats.json" rays_total 2>/dev/null || echo "?")
    printf '%-44s %10s %10.3f %8.2f %12s\n' "$(basename "$scene")" "$d" "$m" \
      "$(echo "$m / $base" | bc -l)" "$rays"
  done
done
