#!/usr/bin/env python3
"""Split a callgrind profile of `dray render` (or `dray bench-rays`) by what the code does.

Reads `callgrind_annotate` output (self cost per "file:function", inlined code counted
under the source file it came from) and sums instructions by category of source file.

Usage:
    valgrind --tool=callgrind --callgrind-out-file=OUT dray render SCENE --workers 0 ...
    python3 benches/profile_split.py OUT [--per N]     # --per: also print per N (rays)
"""

from __future__ import annotations

import argparse
import re
import subprocess
from collections import defaultdict

# First match wins: (category, regex on the source file of the costed line, regex on the
# function it was inlined into). Library code (glam, core, stdarch) inlined into a dray
# function counts for that function.
CATEGORIES = [
    ("traversal: node test + loop",
     r"core/src/bvh/(traverse|node_test|wide)\.rs|obvhs-[^/]+/src/cwbvh/(simd|node|mod|traverse_macro)\.rs|obvhs-[^/]+/src/faststack\.rs",
     r"dray_core::bvh::walk|dray_core::bvh::node_test"),
    ("traversal: triangle test", r"core/src/bvh/leaf\.rs|core/src/intersect\.rs", r"dray_core::intersect::"),
    ("traversal: query setup (bvh.rs, trace.rs, domain.rs)", r"core/src/bvh\.rs|core/src/trace\.rs|core/src/domain\.rs",
     r"dray_core::bvh::Accel::(closest|occluded|prepare)|dray_core::trace::|dray_core::domain::"),
    ("BVH build", r"core/src/bvh/build\.rs|obvhs-[^/]+/src/(cwbvh/bvh2_to_cwbvh|aabb|bvh2|ploc)",
     r"dray_core::bvh::(build|Accel::build)|obvhs::"),
    ("shading: BSDF, material, surface, texture", r"core/src/(bsdf|material|surface|texture)\.rs",
     r"dray_core::(bsdf|material|surface|texture)::"),
    ("light sampling", r"core/src/light[^/]*\.rs", r"dray_core::light"),
    ("sampling (RNG, warps)", r"core/src/sampling\.rs", r"dray_core::sampling::"),
    ("integrator", r"core/src/(integrator|ray)\.rs", r"dray_core::(integrator|ray)::"),
    ("film", r"core/src/film\.rs", r"dray_core::film::"),
    ("camera, render loop", r"core/src/(camera|render)\.rs", r"dray_core::(camera|render)::"),
    ("allocation, memcpy (libc)", r"malloc|memcpy|memmove|memset|libc\.so|alloc/src", r"malloc|free|memcpy|memmove|alloc::"),
    ("scene load", r"scene-loader/|tobj|gltf|ply", r"dray_scene::"),
    ("actors, gRPC, tokio", r"worker/|coordinator/|net/|proto/|tonic|tokio|hyper|h2-|prost",
     r"dray_worker|dray_coordinator|dray_net|tonic|tokio|hyper|h2::|prost"),
]
# Source files that are someone else's code inlined into ours: categorised by function.
LIBRARY = r"glam-[^/]+/|/rustc/|library/core|library/std|stdarch"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("profile")
    ap.add_argument("--per", type=float, help="also print instructions per this many units (e.g. rays)")
    a = ap.parse_args()
    out = subprocess.run(["callgrind_annotate", "--threshold=100", "--auto=no", a.profile], capture_output=True,
                         text=True, check=True).stdout
    total = None
    sums: dict[str, int] = defaultdict(int)
    line_re = re.compile(r"^\s*([\d,]+)\s+\([ \d.]+%\)\s+(\S.*)$")
    in_table = False
    for line in out.splitlines():
        if "PROGRAM TOTALS" in line:
            total = int(line.split()[0].replace(",", ""))
            continue
        if line.startswith("Ir") and "file:function" in line:
            in_table = True
            continue
        if in_table:
            if line.startswith("--"):
                if sums:
                    break
                continue
            m = line_re.match(line)
            if not m:
                continue
            ir = int(m.group(1).replace(",", ""))
            what = m.group(2)
            src, _, func = what.partition(":")
            func = func.split(" [")[0]
            if re.search(LIBRARY, src) and re.search(r"dray_core::bvh::Accel::(closest|occluded)", func):
                # Everything was inlined into the query (the obvhs traversal): node and
                # triangle arithmetic cannot be told apart.
                sums["traversal: library arithmetic inlined into Accel::closest"] += ir
                continue
            if "WatertightRay::new" in func:
                # The watertight ray's per-ray permutation: set-up, not a triangle test.
                sums["traversal: query setup (bvh.rs, trace.rs, domain.rs)"] += ir
                continue
            lib = re.search(LIBRARY, src)
            cat = next((c for c, file_rx, _ in CATEGORIES if not lib and re.search(file_rx, src)), None)
            if cat is None:
                cat = next((c for c, _, func_rx in CATEGORIES if re.search(func_rx, func)), None)
            sums[cat or "other: " + (func or src)[:60]] += ir
    assert total, "no PROGRAM TOTALS in the profile"
    rows = sorted(sums.items(), key=lambda kv: -kv[1])
    print(f"| category | instructions | share{' | per unit' if a.per else ''} |")
    print(f"|---|---:|---:{'|---:' if a.per else ''}|")
    shown = 0
    for cat, ir in rows:
        if ir / total < 0.005 and cat.startswith("other"):
            continue
        shown += ir
        extra = f" | {ir / a.per:,.0f}" if a.per else ""
        print(f"| {cat} | {ir:,} | {100 * ir / total:.1f}%{extra} |")
    rest = total - shown
    extra = f" | {rest / a.per:,.0f}" if a.per else ""
    print(f"| other (each < 0.5%) | {rest:,} | {100 * rest / total:.1f}%{extra} |")
    extra = f" | {total / a.per:,.0f}" if a.per else ""
    print(f"| **total** | {total:,} | 100%{extra} |")


if __name__ == "__main__":
    main()
