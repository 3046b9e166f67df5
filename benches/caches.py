#!/usr/bin/env python3
"""Little 2011's Table 5.1 (ray caches on a 3x3x3 grid of Stanford bunnies), reproduced
with `dray sweep` (docs/caches.md; results in docs/benchmarks.md, "Ray caches").

The scene is `grid:<bunny>:3x3x3` (69,451 x 27 = 1,875,177 triangles), cut once into a
scene package of 27 grid domains (`dray partition --grid 3x3x3 --layout grid`), rendered
with `raycast` (primary rays, direct light, shadow rays) at SIZE x SIZE, 1 spp, for every
lookup radius r and coarse-pass size, on a local `dray cluster --workers W` (`dray sweep
--coordinator`) and in embedded mode (`dray sweep --workers W`). `dray sweep` renders the
exact image first, then every setting, and writes results.csv, table.md and pareto.png
(error against time) per mode; this script prints the table side by side with the
thesis's numbers.

Units: the thesis's voxels are 0.3 wide; ours are the bunny grid's domains, about 0.137
wide, so radii are given in the thesis's units and scaled by (our voxel width / 0.3),
about 0.456 (the script prints it).
The thesis's "cos phi = 0.005" is read as 1 - cos(phi) = 0.005, an angle of 5.73
degrees (a cosine of 0.005 would accept almost any direction).

Usage (from the repository root):
    benches/caches.sh                        # builds dray, then runs this (1024^2)
    python3 benches/caches.py --quick        # 256^2, fewer radii: to try it out
    python3 benches/caches.py --size 1024 --modes cluster --coarse 0 256
    python3 benches/caches.py --modes cluster --links none bandwidth=1gbit,latency=100us
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import os
import subprocess
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _bench_env as env  # noqa: E402

#: Little 2011, Table 5.1 (27 processes, 1024^2): radius -> (seconds, RMS error).
THESIS = {
    "exact": (13.12, 0.0),
    0.001: (13.43, None),
    0.003: (7.73, 0.0887),
    0.005: (6.62, 0.111),
}
THESIS_VOXEL = 0.3
ANGLE_DEG = math.degrees(math.acos(1.0 - 0.005))


def voxel_width(package: Path) -> float:
    """The narrowest domain width of the package's grid (the manifest's bounds / 3)."""
    m = json.loads((package / "manifest.json").read_text())["body"]
    lo, hi = m["bounds"]["min"], m["bounds"]["max"]
    return min((hi[i] - lo[i]) / 3.0 for i in range(3))


def sweep(dray: Path, scene: str, out: Path, size: int, varies: list[str], base: list[str],
          target: list[str], repeat: int, integrator: str = "raycast") -> list[dict]:
    cmd = [str(dray), "sweep", scene, "--integrator", integrator, "--width", str(size),
           "--height", str(size), "--spp", "1", *base, *target, "--repeat", str(repeat),
           "--out", str(out)]
    for v in varies:
        cmd += ["--vary", v]
    print("+", " ".join(cmd), flush=True)
    subprocess.run(cmd, check=True)
    with open(out / "results.csv") as f:
        return list(csv.DictReader(f))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--size", type=int, default=1024)
    ap.add_argument("--radii", type=float, nargs="+",
                    default=[0.001, 0.002, 0.003, 0.004, 0.005, 0.006, 0.007, 0.008, 0.009],
                    help="lookup radii in the thesis's units (voxels 0.3 wide)")
    ap.add_argument("--coarse", type=int, nargs="+", default=[0, 128, 256])
    ap.add_argument("--workers", type=int, default=4)
    ap.add_argument("--placements", nargs="+", default=["sender"],
                    choices=["sender", "remote"],
                    help="ray-cache.placement values to compare (docs/caches.md, \"Placement\")")
    ap.add_argument("--modes", nargs="+", default=["cluster", "embedded"],
                    choices=["cluster", "embedded"])
    ap.add_argument("--links", nargs="+", default=["none"],
                    help="cluster mode: --emulate-link specs, one cluster each (none: plain "
                         "loopback), e.g. bandwidth=1gbit,latency=100us")
    ap.add_argument("--fills", nargs="+", default=["true"], choices=["true", "false"],
                    help="ray-cache.fill values (false: only the coarse pass stores)")
    ap.add_argument("--schedule", default="dynamic",
                    help="every render's --schedule (default dynamic: the thesis's set-up, domains "
                         "owned and rays exchanged; auto, dray's default, replicates this scene on "
                         "every worker for the exact render, which then sends no ray to cache)")
    ap.add_argument("--no-retrieve", action="store_true",
                    help="skip the retrieval-method sweep")
    ap.add_argument("--port", type=int, default=53100)
    ap.add_argument("--work", type=Path, default=Path("benches/out/caches"))
    ap.add_argument("--repeat", type=int, default=3,
                    help="interleaved rounds per sweep; times are medians (dray sweep --repeat)")
    ap.add_argument("--quick", action="store_true", help="256^2, 3 radii, coarse 0 and 64")
    a = ap.parse_args()
    if a.quick:
        a.size, a.radii, a.coarse = 256, [0.001, 0.003, 0.005], [0, 64]
    dray = env.dray_binary()
    bunny = env.bunny()
    package = env.bunny_grid_package(dray, a.work)
    scale = voxel_width(package) / THESIS_VOXEL
    radii = ",".join(f"{r * scale:.6g}" for r in a.radii)
    coarse = ",".join(str(c) for c in a.coarse)
    base = ["--ray-cache", f"angle-deg={ANGLE_DEG:.4g}", "--schedule", a.schedule]
    results: dict[str, list[dict]] = {}
    runs = [(m, link) for m in a.modes for link in (a.links if m == "cluster" else ["none"])]
    for i, (mode, link) in enumerate(runs):
        cluster = None
        name = mode if link == "none" else f"{mode}-{link.replace(',', '-').replace('=', '')}"
        if mode == "cluster":
            extra = ["--threads", "1"]
            if link != "none":
                extra += ["--emulate-link", link]
            cluster = env.Cluster(dray, a.workers, a.port + 20 * i, a.work,
                                  a.work / f"{name}.log", extra)
            target = ["--coordinator", cluster.addr]
        else:
            target = ["--workers", str(a.workers)]
        try:
            # The cluster renders the package (cut once); the embedded mode loads and
            # cuts the scene in memory once, and its workers keep the domains between
            # settings (`dray sweep` in one process keeps them, as a warm cluster does).
            # (the coordinator resolves scene names against its scene root, a.work)
            scene = package.name if mode == "cluster" else f"grid:{bunny}:3x3x3"
            if mode == "embedded":
                target += ["--domains", "27", "--layout", "grid"]
            results[name] = sweep(dray, scene, a.work / f"{name}-radius", a.size,
                                  [f"ray-cache.radius={radii}", f"ray-cache.coarse={coarse}",
                                   f"ray-cache.placement={','.join(a.placements)}",
                                   f"ray-cache.fill={','.join(a.fills)}"],
                                  base, target, a.repeat)
            if not a.no_retrieve:
                mid = f"{0.005 * scale:.6g}"
                results[name + "-retrieve"] = sweep(
                    dray, scene, a.work / f"{name}-retrieve", a.size,
                    ["ray-cache.retrieve=first,nearest,average"],
                    ["--ray-cache", f"angle-deg={ANGLE_DEG:.4g},radius={mid},coarse={max(a.coarse)}",
                     "--schedule", a.schedule],
                    target, a.repeat)
        finally:
            if cluster:
                cluster.stop()
    (a.work / "results.json").write_text(json.dumps(
        {"size": a.size, "workers": a.workers, "scale": scale, "angle_deg": ANGLE_DEG,
         "results": results}, indent=1))
    print(f"\nvoxel {voxel_width(package):.4f} (thesis 0.3): radii scaled by {scale:.4f}; "
          f"angle {ANGLE_DEG:.2f} deg; {a.size}^2 raycast, {a.workers} workers\n")
    for mode, rows in results.items():
        print(f"### {mode}\n")
        print(f"{len(rows)} rows; medians of {a.repeat}\n")
        print("| setting | thesis r | wall s | render s | speedup (render) | CPU s | bytes total | outer hit | inner hit | rays sent | RMS | FLIP | thesis s | thesis RMS |")
        print("|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
        exact_render = next((float(r["render_s"]) for r in rows if r["setting"] == "exact"), None)
        for r in rows:
            radius = r.get("ray-cache.radius") or ""
            thesis_r = round(float(radius) / scale, 4) if radius and r["setting"] != "exact" else None
            key = "exact" if r["setting"] == "exact" else thesis_r
            t = THESIS.get(key) if (r.get("ray-cache.coarse") in (None, "", "256") or key == "exact") else None
            render = float(r["render_s"])
            speed = exact_render / render if exact_render and render > 0 else float("nan")
            ratio = lambda k: f"{float(r[k]):.3f}" if r.get(k) else ""
            print(f"| {r['setting']} | {thesis_r if thesis_r is not None else ''} | "
                  f"{float(r['wall_s']):.2f} | {render:.2f} | {speed:.2f} | "
                  f"{float(r.get('cpu_s') or 'nan'):.2f} | {int(r.get('bytes_total') or 0):,} | "
                  f"{ratio('outer_hit_ratio')} | {ratio('inner_hit_ratio')} | {r.get('rays_sent', '')} | "
                  f"{float(r['rmse']):.4f} | {float(r['flip']):.4f} | "
                  f"{t[0] if t else ''} | {t[1] if t and t[1] is not None else ''} |")
        print()
    return 0


if __name__ == "__main__":
    sys.exit(main())
