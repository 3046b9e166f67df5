#!/usr/bin/env python3
"""The scheduling experiment (docs/benchmarks.md, "Scheduling"): the three schedules of
Navratil et al. 2012 on a scene larger than one worker's memory budget.

A procedural scene (default `grid:spheres:1000:mirror:4x4x4`, 20.5M triangles: mirror and
Lambert spheres, a sun and a point light) is cut once per domain count into a scene
package (`dray partition`), then rendered by a local `dray cluster --workers W` whose
workers each have `--memory-budget` (default: an eighth of the scene's resident size, so
no worker can hold more than an eighth of it and the cluster as a whole cannot hold it
all), with and without `--load-delay-ms` (slow shared storage). For every schedule
(image-plane, domain, dynamic; optionally dynamic with --replicate), integrator (whitted
with two lights and mirror bounces, path) and image size, `dray submit --stats` records:
seconds per frame (the job's time from the coordinator), domain loads and load seconds, evictions, rays exchanged between
workers (64 bytes each), rays forwarded, scheduler rounds and routing versions.
Every image of one (integrator, size) must be the same bytes whatever the schedule: the
script checks it and says so in the table.

Results go to benches/out/scheduling/results.json and a markdown table on stdout;
`--plot FILE.png` draws seconds and domain loads per schedule (matplotlib, installed into
the benchmark venv).

Usage (from the repository root):
    benches/scheduling.sh                              # builds dray, then runs this
    python3 benches/scheduling.py --quick              # a small scene, to try it out
    python3 benches/scheduling.py --domains-per-worker 2 8 32 --sizes 512 --delays 0 50
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import re
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _bench_env as env  # noqa: E402

SCHEDULES = ["image-plane", "domain", "dynamic"]


def sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()[:16]


def partition(dray: Path, scene: str, domains: int, out: Path) -> dict:
    if (out / "manifest.json").exists():
        env.log(f"reusing {out}")
    else:
        env.log(f"partitioning {scene} into {domains} domains -> {out}")
        env.run_timed([dray, "partition", scene, "--domains", str(domains), "--layout", "kd",
                       "--out", out])
    manifest = json.loads((out / "manifest.json").read_text())
    body = manifest.get("body", manifest)
    doms = body["domains"]
    tris = sum(d["triangles"] for d in doms)
    verts = sum(d["vertices"] for d in doms)
    # The worker's resident estimate (dray_scene::partition::resident::resident_bytes).
    resident = [d["vertices"] * 48 + d["triangles"] * (20 + 64) for d in doms]
    return {"triangles": tris, "vertices": verts, "resident_bytes": sum(resident),
            "largest_domain_bytes": max(resident), "domains": len(doms)}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", default="grid:spheres:1000:mirror:4x4x4")
    ap.add_argument("--workers", type=int, default=4)
    ap.add_argument("--threads", type=int, default=1, help="tracing threads per worker")
    ap.add_argument("--domains-per-worker", type=int, nargs="+", default=[16])
    ap.add_argument("--sizes", type=int, nargs="+", default=[512])
    ap.add_argument("--integrators", nargs="+", default=["whitted", "path"])
    ap.add_argument("--spp", type=int, default=1)
    ap.add_argument("--delays", type=int, nargs="+", default=[0, 100], help="--load-delay-ms values")
    ap.add_argument("--budget-fraction", type=float, default=0.125,
                    help="each worker's --memory-budget as a fraction of the scene's resident size")
    ap.add_argument("--schedules", nargs="+", default=SCHEDULES + ["dynamic+replicate"])
    ap.add_argument("--quick", action="store_true", help="a small scene and one setting")
    ap.add_argument("--work", type=Path, default=env.OUT / "scheduling")
    ap.add_argument("--port", type=int, default=52100)
    ap.add_argument("--plot", type=Path)
    ap.add_argument("--replot", type=Path, nargs="+", metavar="RESULTS_JSON",
                    help="render nothing: print the table of these results files together "
                         "(and --plot them)")
    a = ap.parse_args()
    if a.replot:
        runs = [r for f in a.replot for r in json.loads(f.read_text())["runs"]]
        table({"runs": runs})
        if a.plot:
            plot({"runs": runs}, a.plot)
        return 0
    if a.plot:
        env.ensure_venv()  # matplotlib; re-executes this script in the venv first
    if a.quick:
        a.scene = "grid:spheres:100:mirror:2x2x2"
        a.sizes = [128]
        a.delays = [0, 20]
        a.integrators = ["whitted"]
    dray = env.dray_binary()
    a.work.mkdir(parents=True, exist_ok=True)
    results = {"machine": env.machine_info(), "args": {k: str(v) for k, v in vars(a).items()}, "runs": []}
    safe = re.sub(r"[^A-Za-z0-9]+", "_", a.scene)
    for dpw in a.domains_per_worker:
        domains = dpw * a.workers
        pkg_dir = a.work / f"{safe}_{domains}"
        info = partition(dray, a.scene, domains, pkg_dir)
        budget = max(int(info["resident_bytes"] * a.budget_fraction), 1)
        # The budget also holds queued rays (a quarter); a domain must fit the rest.
        if info["largest_domain_bytes"] > budget * 3 // 4:
            env.log(f"{domains} domains: the largest domain ({info['largest_domain_bytes']} B) does not fit "
                    f"a budget of {budget} B; raising the budget to fit it")
            budget = info["largest_domain_bytes"] * 4 // 3 + (1 << 20)
        env.log(f"{domains} domains, {info['triangles']} triangles, resident {info['resident_bytes'] / 2**20:.0f} MiB,"
                f" budget {budget / 2**20:.0f} MiB per worker")
        for delay in a.delays:
            extra = ["--memory-budget", str(budget), "--load-delay-ms", str(delay)]
            if a.threads:
                extra += ["--threads", str(a.threads)]
            cl = env.Cluster(dray, a.workers, a.port, a.work,
                             a.work / f"cluster_{domains}_{delay}.log", extra)
            try:
                for integ in a.integrators:
                    for size in a.sizes:
                        images = {}
                        for sched in a.schedules:
                            name, _, extra = sched.partition("+")
                            tag = f"{domains}d_{delay}ms_{integ}_{size}_{sched}"
                            png = a.work / f"{tag}.png"
                            stats = a.work / f"{tag}.json"
                            cmd = [dray, "submit", "--coordinator", cl.addr, pkg_dir.name,
                                   "--integrator", integ, "--width", str(size), "--height", str(size),
                                   "--spp", str(a.spp), "--max-depth", "3", "--schedule", name,
                                   "--output", png, "--stats", stats, "-q"]
                            if extra == "replicate":
                                cmd.append("--replicate")
                            env.log(f"{tag} ...")
                            r = env.run_timed(cmd, check=False)
                            run = {"domains": domains, "domains_per_worker": dpw, "delay_ms": delay,
                                   "integrator": integ, "size": size, "schedule": sched,
                                   "budget_bytes": budget, "wall_s": r["wall_s"], "ok": r["rc"] == 0}
                            if run["ok"]:
                                s = json.loads(stats.read_text())
                                # The job's own time (submit's wall time is rounded up to its
                                # progress polling).
                                run["job_s"] = s.get("job_time_s")
                                run.update({k: s.get(k) for k in [
                                    "domain_loads", "domain_load_seconds", "evictions", "rays_exchanged",
                                    "rays_forwarded", "scheduler_rounds", "routing_version", "queue_peak"]})
                                run["bytes_exchanged"] = (s.get("rays_exchanged") or 0) * 64
                                run["png"] = sha(png)
                                images[sched] = run["png"]
                            else:
                                run["error"] = r["stderr"].strip().splitlines()[-1:]
                            env.log(f"  {run}")
                            results["runs"].append(run)
                        same = len(set(images.values())) <= 1
                        for run in results["runs"]:
                            if (run["domains"], run["delay_ms"], run["integrator"], run["size"]) == \
                                    (domains, delay, integ, size):
                                run["same_bits"] = same
            finally:
                cl.stop()
    out = a.work / "results.json"
    out.write_text(json.dumps(results, indent=2))
    table(results)
    env.log(f"results in {out}")
    if a.plot:
        plot(results, a.plot)
    return 0


def table(results: dict) -> None:
    print("| domains | delay ms | integrator | size | schedule | s | loads | load s | evictions | MB exchanged | same bits |")
    print("|---:|---:|---|---:|---|---:|---:|---:|---:|---:|---|")
    for r in results["runs"]:
        if not r["ok"]:
            print(f"| {r['domains']} | {r['delay_ms']} | {r['integrator']} | {r['size']} | {r['schedule']} | failed: {r.get('error')} |")
            continue
        print(f"| {r['domains']} | {r['delay_ms']} | {r['integrator']} | {r['size']} | {r['schedule']} | "
              f"{r['job_s'] or r['wall_s']:.2f} | {r['domain_loads']} | {r['domain_load_seconds'] or 0:.1f} | {r['evictions']} | "
              f"{r['bytes_exchanged'] / 1e6:.1f} | {'yes' if r.get('same_bits') else 'NO'} |")


def plot(results: dict, path: Path) -> None:
    import matplotlib  # noqa: PLC0415
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # noqa: PLC0415
    runs = [r for r in results["runs"] if r["ok"]]
    keys = sorted({(r["domains"], r["delay_ms"], r["integrator"], r["size"]) for r in runs})
    scheds = sorted({r["schedule"] for r in runs}, key=lambda s: (SCHEDULES + [s]).index(s))
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.5))
    width = 0.8 / max(len(scheds), 1)
    for i, s in enumerate(scheds):
        xs = [k for k in range(len(keys))]
        secs = [next((r.get("job_s") or r["wall_s"] for r in runs if (r["domains"], r["delay_ms"], r["integrator"], r["size"]) == key
                      and r["schedule"] == s), 0) for key in keys]
        loads = [next((r["domain_loads"] for r in runs if (r["domains"], r["delay_ms"], r["integrator"], r["size"]) == key
                       and r["schedule"] == s), 0) for key in keys]
        axes[0].bar([x + i * width for x in xs], secs, width, label=s)
        axes[1].bar([x + i * width for x in xs], loads, width, label=s)
    labels = [f"{d}d {dl}ms\n{i} {sz}" for d, dl, i, sz in keys]
    for ax, title in zip(axes, ["seconds per frame", "domain loads"]):
        ax.set_xticks([x + width * (len(scheds) - 1) / 2 for x in range(len(keys))])
        ax.set_xticklabels(labels, fontsize=7)
        ax.set_title(title)
        ax.legend(fontsize=8)
    axes[1].set_yscale("log")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    env.log(f"plot in {path}")


if __name__ == "__main__":
    sys.exit(main())
