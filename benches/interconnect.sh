#!/usr/bin/env bash
# Price a distributed render's communication on one machine (docs/caches.md, "Pricing
# communication: the emulated interconnect"): one local `dray cluster` of N workers per link setting, every member started with `--emulate-link
# SPEC` (the dray-net shim: each connection a member's servers accept gets a delay line
# and a token bucket each way; `none` is plain loopback), the same exact job rendered on
# each, rounds interleaved across the clusters after one warm-up job each (warm domains).
# Prints, per setting, the medians of wall time (submit to image written), the
# coordinator's job time, and CPU seconds (user+sys of every process: the cluster's
# members from /proc, plus the `dray submit` client), with ratios against the first
# setting, and whether every setting gave the same image bits.
#
# Default scene: the 3x3x3 bunny grid cut into 27 grid domains, as benches/caches.py
# makes it (the package is shared with it under benches/out/caches); raycast, 1 spp.
#
# Usage: benches/interconnect.sh [--workers N] [--link SPEC]... [--rounds R] [--size PX]
#                                [--scene SCENE --scene-root DIR] [--domains N]
# Each option also has an environment variable: WORKERS, LINKS (space-separated specs),
# ROUNDS, SIZE. Example:
#   LINKS="none bandwidth=1gbit,latency=100us bandwidth=10gbit,latency=20us" benches/interconnect.sh
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."
if [ -z "${DRAY_BIN:-}" ]; then
    cargo build --release -p dray
fi
exec python3 - "$@" <<'PY'
import argparse
import json
import os
import statistics
import subprocess
import sys
from pathlib import Path

sys.path.insert(0, "benches")
import _bench_env as env  # noqa: E402

ap = argparse.ArgumentParser(prog="benches/interconnect.sh")
ap.add_argument("--workers", type=int, default=int(os.environ.get("WORKERS", 4)))
ap.add_argument("--link", action="append", dest="links",
                help="an --emulate-link SPEC, or none (repeatable; default: none and "
                     "bandwidth=1gbit,latency=100us)")
ap.add_argument("--rounds", type=int, default=int(os.environ.get("ROUNDS", 5)))
ap.add_argument("--size", type=int, default=int(os.environ.get("SIZE", 256)))
ap.add_argument("--scene", help="a scene the coordinator reads (default: the bunny grid package)")
ap.add_argument("--scene-root", type=Path, help="the coordinators' --scene-root for --scene")
ap.add_argument("--domains", type=int, help="dray submit --domains (procedural scenes)")
ap.add_argument("--integrator", default="raycast")
ap.add_argument("--spp", type=int, default=1)
ap.add_argument("--threads", type=int, default=1, help="tracing threads per worker")
ap.add_argument("--port", type=int, default=53400)
ap.add_argument("--work", type=Path, default=Path("benches/out/interconnect"))
a = ap.parse_args()
links = a.links or os.environ.get("LINKS", "none bandwidth=1gbit,latency=100us").split()

dray = env.dray_binary()
a.work.mkdir(parents=True, exist_ok=True)
if a.scene:
    scene, root = a.scene, (a.scene_root or a.work).resolve()
else:
    root = Path("benches/out/caches").resolve()
    scene = env.bunny_grid_package(dray, root).name


def tree_cpu_s(pid: int) -> float:
    """User+sys seconds of `pid` and all its descendants (threads included)."""
    children: dict[int, list[int]] = {}
    times: dict[int, float] = {}
    tick = os.sysconf("SC_CLK_TCK")
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            stat = Path(f"/proc/{entry}/stat").read_text()
        except OSError:
            continue
        fields = stat[stat.rindex(")") + 2:].split()
        children.setdefault(int(fields[1]), []).append(int(entry))
        times[int(entry)] = (int(fields[11]) + int(fields[12])) / tick
    total, todo = 0.0, [pid]
    while todo:
        p = todo.pop()
        total += times.get(p, 0.0)
        todo.extend(children.get(p, []))
    return total


job = ["--width", str(a.size), "--height", str(a.size), "--spp", str(a.spp),
       "--integrator", a.integrator, "-q"]
if a.domains:
    job += ["--domains", str(a.domains)]
clusters, rows = [], {spec: [] for spec in links}
load = env.OtherLoad()
try:
    for i, spec in enumerate(links):
        extra = ["--threads", str(a.threads)]
        if spec != "none":
            extra += ["--emulate-link", spec]
        port = a.port + i * (a.workers + 10)
        env.log(f"cluster {i}: {a.workers} workers, link {spec}, port {port}")
        clusters.append(env.Cluster(dray, a.workers, port, root, a.work / f"cluster-{i}.log", extra))

    def render(i: int, spec: str) -> dict:
        c = clusters[i]
        out, stats = a.work / f"link-{i}.png", a.work / f"link-{i}.json"
        before = tree_cpu_s(c.p.pid)
        r = env.run_timed([dray, "submit", "--coordinator", c.addr, scene, *job,
                           "--output", out, "--stats", stats])
        members = tree_cpu_s(c.p.pid) - before
        s = json.loads(stats.read_text())
        return {"wall_s": r["wall_s"], "job_s": s["job_time_s"], "members_cpu_s": members,
                "client_cpu_s": r["cpu_s"], "cpu_s": members + r["cpu_s"]}

    for i, spec in enumerate(links):
        render(i, spec)  # warm-up: loads the domains
    for rnd in range(a.rounds):
        for i, spec in enumerate(links):
            rows[spec].append(render(i, spec))
        env.log(f"round {rnd + 1}/{a.rounds} done")
finally:
    for c in clusters:
        c.stop()

images = [(a.work / f"link-{i}.png").read_bytes() for i in range(len(links))]
same = all(img == images[0] for img in images)
med = {spec: {k: statistics.median(r[k] for r in rs) for k in rs[0]} for spec, rs in rows.items()}
base = med[links[0]]
print(f"\n{scene}, {a.size}x{a.size} {a.integrator} {a.spp} spp, {a.workers} workers x "
      f"{a.threads} thread(s); medians of {a.rounds} interleaved rounds; link = dray-net shim "
      f"(--emulate-link)\n")
print(f"| link | wall s | job s | CPU s (all processes) | wall vs {links[0]} | CPU vs {links[0]} |")
print("|---|---:|---:|---:|---:|---:|")
for spec in links:
    m = med[spec]
    print(f"| {spec} | {m['wall_s']:.3f} | {m['job_s']:.3f} | {m['cpu_s']:.2f} | "
          f"{m['wall_s'] / base['wall_s']:.2f}x | {m['cpu_s'] / base['cpu_s']:.2f}x |")
print(f"\nsame image bits on every link: {'yes' if same else 'NO'}")
env.save_results(a.work / "results.json", env.machine_info(), a,
                 {"links": links, "medians": med, "rounds": rows, "same_bits": same}, load)
sys.exit(0 if same else 1)
PY
