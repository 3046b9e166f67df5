#!/usr/bin/env python3
"""Validate benches/sim/replay.py against real runs on this machine (docs/caches.md
"Simulation at scale: validation").

For each worker count N: ROUNDS renders of one job with `dray render --workers N
--trace-out`, measured by the job's wall time (the trace's `job` line); the trace of the
first round is replayed on one host of this machine's cores (`--one-host`) and its
prediction compared with the median of the other rounds (so the trace replayed is not
the run it is judged against). Then the trace recorded at the largest N is replayed at
every other N (domains re-dealt), against those N's medians.

    benches/sim/run.sh validate.py [--workers 2,4,8] [--rounds 5] [-- render flags]

Prints a Markdown table: N, the measured median (and the spread of the rounds), the
replay of its own trace, of the largest N's trace, and the errors; first on dedicated
cores, then calibrated to the share of the cores that other processes left the render
(/proc/stat's busy time over each round, less the render's own CPU: on a shared
machine the replay's cores are slowed to that share, `replay.py --speed`).
"""

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

HERE = Path(__file__).resolve().parent
REPO = HERE.parent.parent
DEFAULT_JOB = ["cornell:glass", "--width", "192", "--height", "192", "--spp", "4",
               "--integrator", "path", "--domains", "8", "--schedule", "domain"]


def dray():
    b = os.environ.get("DRAY_BIN")
    return b or str(REPO / "target" / "release" / "dray")


def busy_seconds():
    """CPU seconds every process of the machine has used (/proc/stat: all but idle and
    iowait)."""
    with open("/proc/stat") as f:
        v = [int(x) for x in f.readline().split()[1:]]
    ticks = os.sysconf("SC_CLK_TCK")
    return (sum(v[:8]) - v[3] - v[4]) / ticks


def record(n, job, out):
    """The job's wall time, and the share of the machine's cores that other processes
    left it meanwhile (1: none used by others)."""
    b0 = busy_seconds()
    subprocess.run([dray(), "render", *job, "-q", "--workers", str(n), "--output", str(out.with_suffix(".png")),
                    "--trace-out", str(out)], check=True)
    b1 = busy_seconds()
    with open(out) as f:
        head = json.loads(f.readline())
    wall = head["wall_ns"] / 1e9
    cores = os.cpu_count()
    # The render process's own CPU is cpu_seconds (its job) plus start-up; what the
    # machine did beyond the process's is the others' (measured over the whole process,
    # so approximate).
    others = max(0.0, (b1 - b0) - head["stats"]["cpu_seconds"])
    span = max(wall, 1e-9) * cores
    return wall, max(0.05, (span - others) / span)


def replay(trace, *args):
    r = subprocess.run([sys.executable, str(HERE / "replay.py"), str(trace), "--json", "--one-host", *args],
                       check=True, capture_output=True, text=True)
    return json.loads(r.stdout)


def main():
    ap = argparse.ArgumentParser(prog="benches/sim/validate.py")
    ap.add_argument("--workers", default="2,4,8")
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("job", nargs="*", help="dray render's scene and flags (default: %s)" % " ".join(DEFAULT_JOB))
    a = ap.parse_args()
    job = a.job or DEFAULT_JOB
    ns = [int(x) for x in a.workers.split(",")]
    if a.rounds < 2:
        raise SystemExit("--rounds: at least 2 (one to replay, the others to judge it by)")
    work = Path(tempfile.mkdtemp(prefix="dray-validate-"))
    walls, free, traces = {}, {}, {}
    # Rounds interleaved across N, so that a change in the machine's load meanwhile
    # touches every N alike.
    for r in range(a.rounds):
        for n in ns:
            t = work / f"n{n}-r{r}.jsonl"
            wall, share = record(n, job, t)
            walls.setdefault(n, []).append(wall)
            free.setdefault(n, []).append(share)
            traces.setdefault(n, t)
    big = max(ns)
    rows = []
    for n in ns:
        judged = walls[n][1:]
        med = statistics.median(judged)
        share = statistics.median(free[n][1:])
        own = replay(traces[n])
        cross = replay(traces[big], "--nodes", str(n)) if n != big else own
        # Calibrated: the cores as fast as the share of them other processes left.
        own_c = replay(traces[n], "--speed", f"{share:.4f}")
        cross_c = replay(traces[big], "--nodes", str(n), "--speed", f"{share:.4f}") if n != big else own_c
        rows.append((n, med, min(judged), max(judged), own["predicted_s"], own["makespan_s"], own["fixed_s"],
                     cross["predicted_s"], share, own_c["predicted_s"], cross_c["predicted_s"]))
    print(f"job: dray render {' '.join(job)} --workers N; {a.rounds} rounds; machine cores: {os.cpu_count()}")
    print()
    print("| workers | measured median (min-max), s | own trace, dedicated cores, s (simulated + fixed) | error | "
          f"{big}-worker trace, dedicated | error | cores left by others | own trace, calibrated | error | "
          f"{big}-worker trace, calibrated | error |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    pct = lambda p, m: f"{100 * (p - m) / m:+.0f}%"
    for n, med, lo, hi, own, mk, fx, cross, share, own_c, cross_c in rows:
        print(f"| {n} | {med:.3f} ({lo:.3f}-{hi:.3f}) | {own:.3f} ({mk:.3f} + {fx:.3f}) | {pct(own, med)} | "
              f"{cross:.3f} | {pct(cross, med)} | {share:.2f} | {own_c:.3f} | {pct(own_c, med)} | "
              f"{cross_c:.3f} | {pct(cross_c, med)} |")


if __name__ == "__main__":
    main()
