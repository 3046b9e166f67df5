#!/usr/bin/env python3
"""Probability hit maps (Bolstad 2017; docs/caches.md, "Replicated maps") with the source's
own settings, priced in every byte between processes, under both placements, on plain
loopback and on an emulated interconnect (docs/benchmarks.md, "Probability hit maps").

The scene is the 3x3x3 bunny grid cut into 27 grid domains (the package benches/caches.py
makes, shared under benches/out/caches), rendered with `raycast` (camera rays, direct
light, shadow rays that cross domains) at SIZE x SIZE, 1 spp, on a local `dray cluster
--workers W` per link setting, with the static `domain` schedule (so the rays each setting
sends are comparable). `dray sweep --coordinator` renders the exact image first, then every
setting, `--repeat` interleaved rounds, times and CPU seconds as medians.

The reference point is Bolstad's: prior 100, thresholds 0.1 and 0.9, shadow rays only, 12
direction bins (`--phm on`), in consistent and inconsistent mode; a smaller prior shows what
deciding sooner trades in error for traffic. `placement=sender` keeps a copy of every map on
every worker (consulted in-process, outcomes merged in batches); `placement=remote` keeps
each map once, beside its domain's owner (a round trip per consulting ray).

Usage (from the repository root; builds nothing: run `cargo build --release -p dray` first
or set DRAY_BIN):
    python3 benches/hit_maps.py                       # 512^2, loopback and 1 Gbit/100 us
    python3 benches/hit_maps.py --size 256 --repeat 3 --links none
"""

from __future__ import annotations

import argparse
import csv
import json
import subprocess
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _bench_env as env  # noqa: E402


def sweep(dray: Path, scene: str, out: Path, a, target: list[str]) -> list[dict]:
    cmd = [str(dray), "sweep", scene, "--integrator", "raycast", "--width", str(a.size),
           "--height", str(a.size), "--spp", "1", "--schedule", "domain",
           "--phm", f"kinds={a.kinds}", *target, "--repeat", str(a.repeat), "--out", str(out),
           "--vary", "phm.placement=" + ",".join(a.placements),
           "--vary", "phm.prior=" + ",".join(str(p) for p in a.priors),
           "--vary", "phm.mode=" + ",".join(a.modes),
           "--vary", "phm.miss=" + ",".join(str(m) for m in a.misses)]
    print("+", " ".join(cmd), flush=True)
    subprocess.run(cmd, check=True)
    with open(out / "results.csv") as f:
        return list(csv.DictReader(f))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--size", type=int, default=512)
    ap.add_argument("--workers", type=int, default=4)
    ap.add_argument("--links", nargs="+", default=["none", "bandwidth=1gbit,latency=100us"],
                    help="--emulate-link specs of the clusters (none: plain loopback)")
    ap.add_argument("--placements", nargs="+", default=["sender", "remote"])
    ap.add_argument("--priors", type=float, nargs="+", default=[100, 10])
    ap.add_argument("--modes", nargs="+", default=["consistent", "inconsistent"])
    ap.add_argument("--misses", type=float, nargs="+", default=[0.1],
                    help="phm.miss thresholds (the source's: 0.1)")
    ap.add_argument("--kinds", default="shadow",
                    help="ray kinds that consult the maps, joined with + (the source's: shadow)")
    ap.add_argument("--tag", default="hit-maps", help="name of the output folders and logs")
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--port", type=int, default=53500)
    ap.add_argument("--work", type=Path, default=Path("benches/out/caches"))
    a = ap.parse_args()
    dray = env.dray_binary()
    package = env.bunny_grid_package(dray, a.work)
    results: dict[str, list[dict]] = {}
    for i, link in enumerate(a.links):
        extra = ["--threads", "1"]
        if link != "none":
            extra += ["--emulate-link", link]
        tag = "loopback" if link == "none" else link.replace(",", "-").replace("=", "")
        cluster = env.Cluster(dray, a.workers, a.port + 20 * i, a.work,
                              a.work / f"{a.tag}-{tag}.log", extra)
        try:
            results[link] = sweep(dray, package.name, a.work / f"{a.tag}-{tag}", a,
                                  ["--coordinator", cluster.addr])
        finally:
            cluster.stop()
    (a.work / f"{a.tag}.json").write_text(json.dumps(
        {"size": a.size, "workers": a.workers, "results": results}, indent=1))
    for link, rows in results.items():
        exact = next(r for r in rows if r["setting"] == "exact")
        e_wall, e_cpu, e_bytes = (float(exact[k]) for k in ("wall_s", "cpu_s", "bytes_total"))
        print(f"\n### {link}: {a.size}^2 raycast, {a.workers} workers, schedule domain, "
              f"kinds {a.kinds}, medians of {a.repeat}\n")
        print("| setting | wall s | vs exact | CPU s | bytes total | vs exact | rays sent | "
              "skipped | occluded | FLIP |")
        print("|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
        for r in rows:
            wall, cpu, b = float(r["wall_s"]), float(r["cpu_s"]), float(r["bytes_total"])
            print(f"| {r['setting']} | {wall:.2f} | {e_wall / wall:.2f}x | {cpu:.2f} | "
                  f"{int(b):,} | {100.0 * (b - e_bytes) / e_bytes:+.1f}% | "
                  f"{int(r['rays_sent']):,} | {r.get('phm_rays_skipped', '')} | "
                  f"{r.get('phm_rays_occluded', '')} | {float(r['flip']):.4f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
