#!/usr/bin/env python3
"""Little 2011's Tables 5.1-5.7 set-up with dray's faithful modes (issue 43), by `dray sweep`.

Table 5.1's scene (`grid:<bunny>:3x3x3`, one grid domain per bunny) rendered the way the
thesis renders it: `--integrator primary` (camera rays only, first hits lit without
shadow rays; docs/caches.md "The `primary` integrator"), a coarse pass at randomized
positions (`ray-cache.coarse-sampling=random`), caches filled during the render too
(`ray-cache.fill=true`, the thesis's; `false`, dray's frozen default, beside it), at the
thesis's radii 0.003 and 0.005 (scaled to our voxels as benches/caches.py scales them) and
its angle (1 - cos = 0.005). The variations of tables 5.2-5.7: the 5x5x5 grid
(125 domains) and coarse passes of 384^2 and 512^2 beside 256^2. Every sweep writes
results.csv with the statistics the thesis reports: `hit_ratio` (inner + outer),
`coarse_seconds` and `bytes_per_process`.

The thesis's numbers are printed only where this repository quotes them (Table 5.1:
exact 13.12 s; r 0.003 7.73 s, RMS 0.0887; r 0.005 6.62 s, RMS 0.111, on 27 processes at
1024^2); the other tables' numbers are not transcribed here.

Usage (from the repository root):
    benches/little_tables.sh                   # builds dray, then runs this (1024^2)
    python3 benches/little_tables.py --quick   # 256^2, 3x3x3 only, coarse 256: a try-out
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _bench_env as env  # noqa: E402
from caches import ANGLE_DEG, THESIS, THESIS_VOXEL, sweep, voxel_width  # noqa: E402


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--size", type=int, default=1024)
    ap.add_argument("--grids", type=int, nargs="+", default=[3, 5],
                    help="bunny grids, N x N x N with one domain per bunny")
    ap.add_argument("--coarse", type=int, nargs="+", default=[256, 384, 512])
    ap.add_argument("--radii", type=float, nargs="+", default=[0.003, 0.005],
                    help="lookup radii in the thesis's units (voxels 0.3 wide)")
    ap.add_argument("--samplings", nargs="+", default=["random", "centres"],
                    choices=["random", "centres"])
    ap.add_argument("--fills", nargs="+", default=["true", "false"],
                    choices=["true", "false"])
    ap.add_argument("--workers", type=int, default=4)
    ap.add_argument("--schedule", default="dynamic")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--work", type=Path, default=Path("benches/out/little_tables"))
    ap.add_argument("--quick", action="store_true",
                    help="256^2, the 3x3x3 grid, coarse 256, r 0.005, one round")
    a = ap.parse_args()
    if a.quick:
        a.size, a.grids, a.coarse, a.radii, a.repeat = 256, [3], [256], [0.005], 1
    dray = env.dray_binary()
    bunny = env.bunny()
    # Radii in the thesis's units, scaled to our voxels (each holds one bunny, whatever
    # the grid), as benches/caches.py does.
    scale = voxel_width(env.bunny_grid_package(dray, a.work)) / THESIS_VOXEL
    radii = ",".join(f"{r * scale:.6g}" for r in a.radii)
    base = ["--ray-cache", f"angle-deg={ANGLE_DEG:.4g}", "--schedule", a.schedule]
    varies = [f"ray-cache.radius={radii}",
              f"ray-cache.coarse={','.join(str(c) for c in a.coarse)}",
              f"ray-cache.coarse-sampling={','.join(a.samplings)}",
              f"ray-cache.fill={','.join(a.fills)}"]
    results = {}
    for grid in a.grids:
        scene = f"grid:{bunny}:{grid}x{grid}x{grid}"
        # Embedded mode: one grid domain per bunny, `primary` at 1 spp.
        target = ["--domains", str(grid ** 3), "--layout", "grid", "--workers",
                  str(a.workers)]
        results[f"{grid}x{grid}x{grid}"] = sweep(
            dray, scene, a.work / f"grid{grid}", a.size, varies, base, target, a.repeat,
            integrator="primary")
    (a.work / "results.json").write_text(json.dumps(
        {"size": a.size, "workers": a.workers, "scale": scale, "angle_deg": ANGLE_DEG,
         "machine": env.machine_info(), "results": results}, indent=1))
    print(f"\nprimary, 1 spp, {a.size}^2, {a.workers} in-process workers, schedule "
          f"{a.schedule}; radii scaled by {scale:.4f}; medians of {a.repeat}\n")
    for name, rows in results.items():
        print(f"### {name} grid\n")
        print("| setting | render s | speed-up | hit ratio (all) | outer | inner | coarse s "
              "| MB per process | RMS | FLIP | thesis s | thesis RMS |")
        print("|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
        exact = next((float(r["render_s"]) for r in rows if r["setting"] == "exact"), None)
        for r in rows:
            render = float(r["render_s"])
            radius = r.get("ray-cache.radius") or ""
            thesis_r = round(float(radius) / scale, 4) if radius else None
            key = "exact" if r["setting"] == "exact" else thesis_r
            # Table 5.1 only: the 3x3x3 grid with the thesis's 256^2 coarse pass.
            t = THESIS.get(key) if name == "3x3x3" and (
                key == "exact" or r.get("ray-cache.coarse") == "256") else None
            cell = lambda k, f="{:.3f}": f.format(float(r[k])) if r.get(k) else ""
            mb = (f"{int(r['bytes_per_process']) / 1e6:.1f}"
                  if r.get("bytes_per_process") else "")
            print(f"| {r['setting']} | {render:.3f} | "
                  f"{(exact / render if exact and render > 0 else float('nan')):.2f} | "
                  f"{cell('hit_ratio')} | {cell('outer_hit_ratio')} | "
                  f"{cell('inner_hit_ratio')} | {cell('coarse_seconds')} | {mb} | "
                  f"{float(r['rmse']):.4f} | {float(r['flip']):.4f} | "
                  f"{t[0] if t else ''} | {t[1] if t and t[1] is not None else ''} |")
        print()
    return 0


if __name__ == "__main__":
    sys.exit(main())
