#!/usr/bin/env python3
"""Speed-up against node count at 1, 10 and 100 Gbit/s, by replay (docs/caches.md
"Simulation at scale: first scaling table"): one trace of the exact render and one with
frozen ray caches, each recorded once here with `dray render --workers W --trace-out`,
then replayed by benches/sim/replay.py on 1 to 64 nodes (domains re-dealt round robin,
one tracing thread per node, 10 us links). Speed-up is the simulated makespan on one node
over that on N nodes (the recording's fixed part left out: it does not scale).

    benches/sim/run.sh scaling.py [--workers 8] [--nodes 1,4,16,64]
"""

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

HERE = Path(__file__).resolve().parent
REPO = HERE.parent.parent
JOB = ["cornell:glass", "--width", "128", "--height", "128", "--spp", "4", "--integrator", "path",
       "--domains", "64", "--schedule", "domain"]
CACHES = ["--ray-cache", "radius=0.05,coarse=64"]


def replay(trace, nodes, bw):
    r = subprocess.run([sys.executable, str(HERE / "replay.py"), str(trace), "--json", "--nodes", str(nodes),
                        "--threads", "1", "--bandwidth", bw, "--latency", "10us"],
                       check=True, capture_output=True, text=True)
    return json.loads(r.stdout)


def main():
    ap = argparse.ArgumentParser(prog="benches/sim/scaling.py")
    ap.add_argument("--workers", type=int, default=8)
    ap.add_argument("--nodes", default="1,4,16,64")
    a = ap.parse_args()
    nodes = [int(x) for x in a.nodes.split(",")]
    work = Path(tempfile.mkdtemp(prefix="dray-scaling-"))
    dray = str(REPO / "target" / "release" / "dray")
    rows = []
    for name, extra in [("exact", []), ("ray caches", CACHES)]:
        t = work / f"{name.replace(' ', '-')}.jsonl"
        subprocess.run([dray, "render", *JOB, *extra, "-q", "--workers", str(a.workers),
                        "--output", str(t.with_suffix(".png")), "--trace-out", str(t)], check=True)
        for bw in ["1Gbps", "10Gbps", "100Gbps"]:
            base = replay(t, 1, bw)["makespan_s"]
            for n in nodes:
                r = replay(t, n, bw)
                rows.append((name, bw, n, r["makespan_s"], base / r["makespan_s"], r["bytes_sent"]))
    print(f"jobs: dray render {' '.join(JOB)} [{' '.join(CACHES)}], recorded on {a.workers} workers")
    print()
    print("| render | link | nodes | simulated s | speed-up | bytes between nodes |")
    print("|---|---|---|---|---|---|")
    for name, bw, n, t, s, b in rows:
        print(f"| {name} | {bw} | {n} | {t:.3f} | {s:.2f} | {b} |")


if __name__ == "__main__":
    main()
