#!/usr/bin/env python3
"""Bolstad 2017's experiment as dray can run it: probability hit maps at the source's own
settings on a path-traced scene lit by an area light, the bytes between processes
counted, the map memory reported, and the spread over repeated runs (hit maps learn
differently each run). docs/caches.md "Bolstad 2017: probability hit maps" lists what is
faithful and what departs.

The scene is the Cornell box (`cornell`: one area light on the ceiling), path traced at
16 spp (Bolstad's sample count) in 8 domains on 4 in-process workers under the static
`domain` schedule (so every setting sends comparable rays), with maps on shadow rays
(`kinds=shadow`), prior 100, thresholds 0.1 / 0.9 and 12 direction bins (Bolstad's), in
consistent and inconsistent mode. `dray sweep` renders the exact image, then each
setting, `--repeat` interleaved rounds: bytes and times are medians, and results.csv's
`*_min` / `*_max` give each measure's least and most over the rounds (a map's decisions
depend on which outcomes arrive first, so its bytes and image move between runs).

Bolstad reports 7.3-18.2% less traffic with hit maps (rays transmitted between servers,
up to 32 servers, 16 spp, 10-100 area-light samples per hit). By default dray's path
integrator takes one light sample per bounce, so a hit sends one shadow ray: the maps
see fewer outcomes per cell. `--light-samples N` passes `dray sweep --light-samples N`
(N shadow rays to the area light per hit, each carrying 1/N of its light; 10 is
Bolstad's least), and writes under `cornell-SIZE-lsN`.

Usage (from the repository root; builds nothing: `cargo build --release -p dray` first or
set DRAY_BIN):
    python3 benches/bolstad.py                 # 256^2, 16 spp, 5 rounds
    python3 benches/bolstad.py --size 128 --repeat 2
    python3 benches/bolstad.py --light-samples 10 --repeat 2
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

# Bolstad 2017's reduction in rays transmitted, as issue 43 quotes it.
BOLSTAD_TRAFFIC = "7.3-18.2% less"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--spp", type=int, default=16)
    ap.add_argument("--domains", type=int, default=8)
    ap.add_argument("--workers", type=int, default=4)
    ap.add_argument("--modes", nargs="+", default=["consistent", "inconsistent"])
    ap.add_argument("--priors", type=float, nargs="+", default=[100])
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--light-samples", type=int, default=1,
                    help="samples of the area light per hit (dray --light-samples; default 1)")
    ap.add_argument("--work", type=Path, default=Path("benches/out/bolstad"))
    a = ap.parse_args()
    if a.repeat < 2:
        raise SystemExit("--repeat: at least 2 (the spread needs more than one run)")
    dray = env.dray_binary()
    # One light sample keeps the command (and the output directory) of the runs before
    # the option existed.
    ls = a.light_samples
    out = a.work / (f"cornell-{a.size}" if ls == 1 else f"cornell-{a.size}-ls{ls}")
    cmd = [str(dray), "sweep", "cornell", "--integrator", "path", "--width", str(a.size),
           "--height", str(a.size), "--spp", str(a.spp), "--domains", str(a.domains),
           "--workers", str(a.workers), "--schedule", "domain",
           "--phm", "kinds=shadow,hit=0.9,miss=0.1",
           "--vary", "phm.prior=" + ",".join(f"{p:g}" for p in a.priors),
           "--vary", "phm.mode=" + ",".join(a.modes),
           "--repeat", str(a.repeat), "--out", str(out)]
    if ls != 1:
        cmd += ["--light-samples", str(ls)]
    print("+", " ".join(cmd), flush=True)
    subprocess.run(cmd, check=True)
    with open(out / "results.csv") as f:
        rows = list(csv.DictReader(f))
    (a.work / "results.json" if ls == 1 else out / "results.json").write_text(json.dumps(
        {"size": a.size, "spp": a.spp, "light_samples": ls, "domains": a.domains, "workers": a.workers,
         "repeat": a.repeat,
         "machine": env.machine_info(), "rows": rows}, indent=1))
    exact = next(r for r in rows if r["setting"] == "exact")
    e_bytes, e_render = float(exact["bytes_total"]), float(exact["render_s"])
    pct = lambda b: 100.0 * (float(b) - e_bytes) / e_bytes
    print(f"\ncornell, path, {a.size}^2, {a.spp} spp, {ls} light sample(s) per hit, {a.domains} domains, "
          f"{a.workers} in-process workers, "
          f"schedule domain; maps on shadow rays, thresholds 0.1 / 0.9; medians (least-most) of {a.repeat} rounds\n")
    print("| setting | bytes between processes | vs exact (least-most) | render s (least-most) | "
          "vs exact | FLIP (least-most) | rays skipped | occluded | map memory | Bolstad |")
    print("|---|---:|---:|---:|---:|---:|---:|---:|---:|---|")
    for r in rows:
        b = float(r["bytes_total"])
        maps = r.get("phm_map_bytes") or ""
        print(f"| {r['setting']} | {int(b):,} | {pct(b):+.1f}% ({pct(r['bytes_total_min']):+.1f}% to "
              f"{pct(r['bytes_total_max']):+.1f}%) | {float(r['render_s']):.3f} ({float(r['render_s_min']):.3f}-"
              f"{float(r['render_s_max']):.3f}) | {e_render / float(r['render_s']):.2f}x | "
              f"{float(r['flip']):.4f} ({float(r['flip_min']):.4f}-{float(r['flip_max']):.4f}) | "
              f"{r.get('phm_rays_skipped', '')} | {r.get('phm_rays_occluded', '')} | "
              f"{int(maps):,} B | {'' if r['setting'] == 'exact' else BOLSTAD_TRAFFIC} |"
              if maps else
              f"| {r['setting']} | {int(b):,} | | {float(r['render_s']):.3f} ({float(r['render_s_min']):.3f}-"
              f"{float(r['render_s_max']):.3f}) | 1.00x | 0 | | | | |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
