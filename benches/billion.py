#!/usr/bin/env python3
"""A billion triangles out of core: partition a procedural scene of more than 10^9
triangles to disk, then render it on a local 4-worker cluster whose memory budgets hold a
small fraction of it, with the dynamic schedule.

Steps (docs/history/2026-11-26-billion-triangles.md has the numbers of the first run):
1. `dray partition SCENE --domains N --layout kd` under wait4, sampling the package
   directory's size every 2 s (its peak is the disk the write needs: spill files plus
   domain files) and the machine's load. Refuses to start when the disk cannot hold the
   package (about 34 bytes a triangle for iso grids, plus 4 for the spill).
2. `dray cluster --workers W --memory-budget B --threads T`, and one
   `dray submit ... --schedule dynamic --stats`, while the coordinator's and each
   worker's VmHWM and VmRSS are read from /proc every second.
3. results.json and a markdown table in --work; the image is copied to --image.
The package (tens of GB) is deleted at the end unless --keep-package.

Took 35 minutes on the project's 2-core, 24 GiB machine at the default size (partition
17 min, render 18 min) with other engineers' builds on the same cores, and needs about
40 GB free under --work (the package is 33 GB); `--quick` runs the same steps on 20
million triangles in about two minutes. Not for CI.

Usage (from the repository root):
    benches/billion.sh                  # builds dray, then runs this
    python3 benches/billion.py --quick  # the same on a small scene
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _bench_env as env  # noqa: E402
from distributed import proc_cpu, proc_mem  # noqa: E402

# 5 x 5 x 5 copies of a 648^3-cell gyroid (about 8.1M triangles each): 1.02 billion.
SCENE = "grid:iso:gyroid:648:5x5x5"
QUICK_SCENE = "grid:iso:gyroid:512:4x1x1"
# Package bytes per triangle for iso grids (about 34: docs/history/2026-11-26-billion-triangles.md),
# plus the 4-byte id spill, with a margin.
BYTES_PER_TRIANGLE = 40


def parse_args() -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", default=SCENE)
    ap.add_argument("--triangles-estimate", type=float, default=1.02e9,
                    help="triangles --scene has, for the disk check")
    ap.add_argument("--domains", type=int, default=1024)
    ap.add_argument("--workers", type=int, default=4)
    ap.add_argument("--budget", default="2G", help="each worker's --memory-budget")
    ap.add_argument("--threads", type=int, default=1, help="tracing threads per worker")
    ap.add_argument("--size", type=int, default=512)
    ap.add_argument("--spp", type=int, default=1)
    ap.add_argument("--integrator", default="whitted")
    ap.add_argument("--max-depth", type=int, default=2)
    ap.add_argument("--port", type=int, default=47900)
    ap.add_argument("--work", type=Path, default=env.OUT / "billion",
                    help="package, logs, image and results go here")
    ap.add_argument("--image", type=Path, help="also copy the image here")
    ap.add_argument("--keep-package", action="store_true")
    ap.add_argument("--reuse-package", action="store_true",
                    help="skip the partition when --work already holds the package")
    ap.add_argument("--submit-timeout", type=float, default=3 * 3600)
    ap.add_argument("--quick", action="store_true", help=f"{QUICK_SCENE}, 256 domains, 64M budgets")
    a = ap.parse_args()
    if a.quick:
        a.scene, a.triangles_estimate, a.domains, a.budget = QUICK_SCENE, 2.1e7, 256, "64M"
    return a


def busy_seconds() -> float:
    """CPU seconds spent by everyone on the machine so far (/proc/stat)."""
    return env._cpu_jiffies()[0] / os.sysconf("SC_CLK_TCK")


def dir_bytes(d: Path) -> int:
    total = 0
    try:
        with os.scandir(d) as it:
            for e in it:
                try:
                    total += e.stat().st_blocks * 512
                except OSError:
                    pass
    except OSError:
        pass
    return total


class Sampler(threading.Thread):
    """Calls `sample()` every `period` s until stopped; keeps the load averages seen."""

    def __init__(self, period: float, sample) -> None:
        super().__init__(daemon=True)
        self.period, self.sample, self.halt = period, sample, threading.Event()
        self.loadavg: list[float] = []

    def run(self) -> None:
        while not self.halt.is_set():
            self.sample()
            self.loadavg.append(os.getloadavg()[0])
            self.halt.wait(self.period)

    def stop(self) -> None:
        self.halt.set()
        self.join()
        self.sample()


def partition(dray: Path, a: argparse.Namespace, pkg: Path) -> dict:
    free = shutil.disk_usage(a.work).free
    need = int(a.triangles_estimate * BYTES_PER_TRIANGLE)
    if free < need:
        sys.exit(f"{a.work}: {free / 1e9:.1f} GB free, the package needs about {need / 1e9:.1f} GB")
    peak = {"bytes": 0}

    def sample() -> None:
        peak["bytes"] = max(peak["bytes"], dir_bytes(pkg))

    cmd = [str(dray), "partition", a.scene, "--domains", str(a.domains), "--layout", "kd", "--out", str(pkg)]
    env.log(" ".join(cmd))
    s = Sampler(2.0, sample)
    busy0, t0 = busy_seconds(), time.perf_counter()
    s.start()
    p = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=open(a.work / "partition.log", "w"), text=True)
    stdout = p.stdout.read()
    _, status, ru = os.wait4(p.pid, 0)
    wall = time.perf_counter() - t0
    s.stop()
    if os.waitstatus_to_exitcode(status) != 0:
        sys.exit(f"dray partition failed; see {a.work / 'partition.log'}")
    ours = ru.ru_utime + ru.ru_stime
    out = env.last_json_line(stdout)
    out.update({
        "command": " ".join(cmd),
        "wall_s": wall,
        "user_s": ru.ru_utime,
        "sys_s": ru.ru_stime,
        "peak_rss_kib": ru.ru_maxrss,
        "written_bytes": ru.ru_oublock * 512,
        "peak_dir_bytes": peak["bytes"],
        "package_dir_bytes": dir_bytes(pkg),
        "other_cores": max(0.0, (busy_seconds() - busy0 - ours) / wall),
        "loadavg_mean": sum(s.loadavg) / max(len(s.loadavg), 1),
        "loadavg_max": max(s.loadavg, default=0.0),
    })
    env.log(f"partition: {json.dumps(out)}")
    return out


def render(dray: Path, a: argparse.Namespace, pkg: Path) -> dict:
    cmd = [str(dray), "cluster", "--workers", str(a.workers), "--base-port", str(a.port),
           "--scene-root", str(a.work), "--memory-budget", a.budget, "--threads", str(a.threads)]
    env.log(" ".join(cmd))
    logf = open(a.work / "cluster.log", "w")
    cl = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=logf, text=True)
    pids: dict[str, int] = {}
    for line in cl.stdout:
        m = re.match(r"(coordinator|worker \d+)\s+\S+\s+pid (\d+)", line)
        if m:
            pids[m.group(1)] = int(m.group(2))
        if line.startswith("dray cluster ready"):
            break
    else:
        sys.exit(f"dray cluster did not start; see {a.work / 'cluster.log'}")
    mem: dict[str, dict] = {name: {} for name in pids}

    def sample() -> None:
        for name, pid in pids.items():
            for k, v in proc_mem(pid).items():
                mem[name][k] = max(mem[name].get(k, 0), v)

    png, stats = a.work / "billion.png", a.work / "stats.json"
    submit = [str(dray), "submit", "--coordinator", f"127.0.0.1:{a.port}", pkg.name,
              "--width", str(a.size), "--height", str(a.size), "--spp", str(a.spp),
              "--integrator", a.integrator, "--max-depth", str(a.max_depth), "--schedule", "dynamic",
              "--output", str(png), "--stats", str(stats)]
    env.log(" ".join(submit))
    s = Sampler(1.0, sample)
    cpu0 = {n: proc_cpu(p) for n, p in pids.items()}
    busy0, t0 = busy_seconds(), time.perf_counter()
    s.start()
    try:
        r = subprocess.run(submit, stdout=subprocess.PIPE, stderr=open(a.work / "submit.log", "w"),
                           text=True, timeout=a.submit_timeout)
        rc = r.returncode
    except subprocess.TimeoutExpired:
        rc = "timeout"
    wall = time.perf_counter() - t0
    cpu = {n: proc_cpu(p) - cpu0[n] for n, p in pids.items()}
    ours = sum(cpu.values())
    other = max(0.0, (busy_seconds() - busy0 - ours) / wall)
    s.stop()
    cl.send_signal(signal.SIGTERM)
    try:
        cl.wait(60)
    except subprocess.TimeoutExpired:
        cl.kill()
        cl.wait()
    logf.close()
    if rc != 0:
        sys.exit(f"dray submit failed ({rc}); see {a.work / 'submit.log'} and {a.work / 'cluster.log'}")
    out = {
        "command": " ".join(submit),
        "cluster_command": " ".join(cmd),
        "submit_wall_s": wall,
        "members": {n: {"VmHWM_mib": m.get("VmHWM"), "VmRSS_max_mib": m.get("VmRSS"),
                        "cpu_s": cpu[n]} for n, m in mem.items()},
        "members_cpu_s": ours,
        "other_cores": other,
        "loadavg_mean": sum(s.loadavg) / max(len(s.loadavg), 1),
        "loadavg_max": max(s.loadavg, default=0.0),
        "stats": json.loads(stats.read_text()),
        "png_bytes": png.stat().st_size,
    }
    if a.image:
        a.image.parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(png, a.image)
    return out


def table(res: dict) -> None:
    p, r = res["partition"], res["render"]
    s = r["stats"]
    print("| scene | triangles | domains | partition s | package GB | partition peak RSS MiB | render s |")
    print("|---|---:|---:|---:|---:|---:|---:|")
    print(f"| `{res['args']['scene']}` | {p['triangles']:,} | {p['domains']} | {p['wall_s']:.0f} | "
          f"{p['bytes'] / 1e9:.1f} | {p['peak_rss_kib'] / 1024:.0f} | {s['job_time_s']:.0f} |")
    print()
    print("| process | VmHWM MiB | CPU s |")
    print("|---|---:|---:|")
    for n, m in r["members"].items():
        hwm = f"{m['VmHWM_mib']:.0f}" if m["VmHWM_mib"] else "?"
        print(f"| {n} | {hwm} | {m['cpu_s']:.0f} |")
    print()
    print(f"domain loads {s.get('domain_loads')}, load seconds {s.get('domain_load_seconds', 0):.0f}, "
          f"evictions {s.get('evictions')}, rays {s.get('rays_total')}, rays exchanged {s.get('rays_exchanged')}")


def main() -> int:
    a = parse_args()
    dray = env.dray_binary()
    a.work = a.work.resolve()
    a.work.mkdir(parents=True, exist_ok=True)
    pkg = a.work / "package"
    res = {"machine": env.machine_info(), "args": {k: str(v) for k, v in vars(a).items()},
           "binary": env.binary_info(dray)}
    try:
        if a.reuse_package and (pkg / "manifest.json").exists():
            env.log(f"reusing {pkg}")
            res["partition"] = json.loads((a.work / "partition.json").read_text())
        else:
            res["partition"] = partition(dray, a, pkg)
            (a.work / "partition.json").write_text(json.dumps(res["partition"], indent=2))
        res["render"] = render(dray, a, pkg)
    finally:
        if not a.keep_package and pkg.exists():
            env.log(f"removing {pkg}")
            shutil.rmtree(pkg)
    (a.work / "results.json").write_text(json.dumps(res, indent=2) + "\n")
    table(res)
    env.log(f"results in {a.work / 'results.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
