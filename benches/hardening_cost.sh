#!/usr/bin/env bash
# What the second hardening round (docs/security.md, "Hardening, second round") costs a
# render: two dray binaries (OLD_BIN, before; NEW_BIN, after) on the same multi-worker
# embedded renders, where every ray batch, report and
# heartbeat crosses the hardened server stack (per-class admission, body deadlines, the
# place held in every response body, connection limits). Runs are interleaved (old, new,
# old, new, ...); prints per case the median wall seconds and median CPU seconds
# (user + sys) of each over RUNS rounds, the new/old ratios, and whether the PNGs are
# bit-identical.
# Usage: OLD_BIN=path NEW_BIN=path [RUNS=5] benches/hardening_cost.sh
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."
: "${OLD_BIN:?set OLD_BIN to the dray binary before the change}"
NEW_BIN="${NEW_BIN:-target/release/dray}"
RUNS="${RUNS:-5}"
out=$(mktemp -d)
trap 'rm -rf "$out"' EXIT

# scene | flags
cases=(
  "grid:spheres:200:2x2x2|--workers 4 --domains 16 --spp 16 --width 320 --height 240"
  "cornell:glass|--workers 4 --domains 16 --spp 16 --max-depth 8 --width 256 --height 256"
)

median() { sort -g | awk '{a[NR]=$1} END {print a[int((NR+1)/2)]}'; }

# run BIN TAG SCENE FLAGS...: appends "wall cpu" of one render to $out/TAG.times
run() {
  local bin=$1 tag=$2 scene=$3; shift 3
  local t0 t1
  t0=$(date +%s.%N)
  /usr/bin/time -f "%U %S" -o "$out/$tag.cpu" "$bin" render "$scene" "$@" -q \
    --output "$out/$tag.png" >/dev/null 2>&1
  t1=$(date +%s.%N)
  read -r u s <"$out/$tag.cpu"
  echo "$(echo "$t1 - $t0" | bc -l) $(echo "$u + $s" | bc -l)" >>"$out/$tag.times"
}

printf '%-28s %8s %8s %6s %8s %8s %6s %s\n' case old_wall new_wall ratio old_cpu new_cpu ratio bits
for c in "${cases[@]}"; do
  scene=${c%%|*}; flags=${c#*|}
  rm -f "$out"/*.times
  for _ in $(seq "$RUNS"); do
    # shellcheck disable=SC2086
    run "$OLD_BIN" old "$scene" $flags
    # shellcheck disable=SC2086
    run "$NEW_BIN" new "$scene" $flags
  done
  ow=$(cut -d' ' -f1 "$out/old.times" | median); nw=$(cut -d' ' -f1 "$out/new.times" | median)
  oc=$(cut -d' ' -f2 "$out/old.times" | median); nc=$(cut -d' ' -f2 "$out/new.times" | median)
  same=$(cmp -s "$out/old.png" "$out/new.png" && echo identical || echo DIFFER)
  printf '%-28s %8.3f %8.3f %6.3f %8.2f %8.2f %6.3f %s\n' "$scene" "$ow" "$nw" \
    "$(echo "$nw / $ow" | bc -l)" "$oc" "$nc" "$(echo "$nc / $oc" | bc -l)" "$same"
done
