#!/usr/bin/env python3
"""Speed-up against node count by replay (docs/caches.md "Simulation at scale: scaling"):
one trace of the exact render and one with frozen ray caches, each recorded once here with
`dray render --workers W --trace-out` (by default one worker per domain, so that every
domain's rays are steps of their own and a replay on up to W nodes misses no traffic),
then replayed by benches/sim/replay.py on 1 to 64 nodes (domains re-dealt round robin, one
tracing thread per node, 10 us links) at each link speed, with the process CPU outside
the steps modelled from the replay's own counts (`--overhead model`: per batch and per ray
sent to another node, and each process's background share of a core; the model
benches/sim/validate.py checks against real runs) and, for comparison, left out
(`--overhead none`). Speed-up is the simulated makespan on one node over that on N nodes
(the recording's fixed part left out: it does not scale). `--fs-bandwidth` adds
Navratil's regime: every first visit of a domain on a node reads it from one shared file
system behind a link of that rate.

    benches/sim/run.sh scaling.py [--job cornell|little] [--workers W] [--nodes 1,2,4,8,16,32,64] \
        [--links 100Mbps,1Gbps,10Gbps] [--fs-bandwidth 1GB/s] [--plot docs/sim-scaling.svg] \
        [--keep DIR | --from DIR]

`--job little` is Little 2011's Table 5.1 set-up (benches/caches.py's scene, radius and
coarse pass; the Stanford bunny from $DRAY_SCENES) on 1, 3, 9 and 27 nodes; `--job bolstad`
hit maps with Bolstad 2017's settings on the Cornell box's area light (path, 16 spp) on 1
to 32 nodes; `--job navratil` Navratil et al. 2012's regime: one recording of the static
`domain` schedule replayed static and with the replay's dynamic schedule (replicas of
the domains with the most rays waiting, loaded from a 1 GB/s shared file system) on 1 to
1,024 nodes.
"""

import argparse
import json
import math
import subprocess
import sys
import tempfile
from pathlib import Path

HERE = Path(__file__).resolve().parent
REPO = HERE.parent.parent
sys.path.insert(0, str(REPO / "benches"))


class Job:
    """A job to record: its flags, its ray caches, its domains, the nodes to replay on."""

    def __init__(self, title, flags, caches, domains, nodes, approx="ray caches", replay_flags=(), fs=None):
        self.title, self.flags, self.caches, self.domains, self.nodes = title, flags, caches, domains, nodes
        self.approx = approx  # what `caches` turns on, as the tables and the plot name it
        # Flags of the replay (not the render) that make the second variant, and the
        # shared file system the job is meant for (None: loads read nothing).
        self.replay_flags, self.fs = list(replay_flags), fs


def navratil():
    """Navratil et al. 2012's regime: domains loaded from a shared parallel file system, the
    image's cost concentrated in a few domains (the glass and what surrounds it), and more
    nodes than domains. One recording of the static `domain` schedule, replayed static
    and with the replay's dynamic schedule (a node with nothing ready gets a replica of
    the domain with the most rays waiting per holder, loaded from the file system)."""
    return Job("64 domains, cornell:glass 256x256, 8 spp, loads from a 1GB/s file system",
               ["cornell:glass", "--width", "256", "--height", "256", "--spp", "8", "--integrator", "path",
                "--domains", "64", "--schedule", "domain"],
               [], 64, "1,4,16,64,256,1024", approx="dynamic", replay_flags=["--schedule", "dynamic"], fs="1GB/s")


def cornell():
    return Job("64 domains, cornell:glass 128x128, 4 spp",
               ["cornell:glass", "--width", "128", "--height", "128", "--spp", "4", "--integrator", "path",
                "--domains", "64", "--schedule", "domain"],
               ["--ray-cache", "radius=0.05,coarse=64"], 64, "1,2,4,8,16,32,64")


def bolstad():
    """Hit maps where Bolstad 2017 says they pay: path tracing at 16 spp with many shadow
    rays (the Cornell box's area light), Bolstad's prior 100 and hit threshold 0.9 on shadow
    rays, 32 domains, replayed on up to Bolstad's 32 servers."""
    return Job("32 domains, cornell path 256x256, 16 spp",
               ["cornell", "--integrator", "path", "--width", "256", "--height", "256", "--spp", "16",
                "--domains", "32", "--schedule", "domain"],
               ["--phm", "kinds=shadow,prior=100,hit=0.9"], 32, "1,2,4,8,16,32", approx="hit maps")


def little(work):
    """Little 2011's Table 5.1 set-up as benches/caches.py runs it (docs/benchmarks.md, "Ray
    caches"): the 3x3x3 bunny grid in 27 grid domains, `raycast` 1024^2, 1 spp, frozen
    caches of the thesis's radius 0.005 (scaled to these voxels) after a 256^2 coarse pass,
    replayed on the thesis's 27 processes and fewer."""
    import _bench_env as env
    from caches import ANGLE_DEG, THESIS_VOXEL, voxel_width

    dray = REPO / "target" / "release" / "dray"
    radius = 0.005 * voxel_width(env.bunny_grid_package(dray, work)) / THESIS_VOXEL
    return Job("27 grid domains, bunny 3x3x3 raycast 1024x1024 (Little's Table 5.1)",
               [f"grid:{env.bunny()}:3x3x3", "--domains", "27", "--layout", "grid", "--integrator", "raycast",
                "--width", "1024", "--height", "1024", "--spp", "1", "--schedule", "domain"],
               ["--ray-cache", f"angle-deg={ANGLE_DEG:.4g},radius={radius:.6g},coarse=256,fill=false"],
               27, "1,3,9,27")


def replay(trace, nodes, bw, overhead, fs=None, extra=()):
    cmd = [sys.executable, str(HERE / "replay.py"), str(trace), "--json", "--nodes", str(nodes),
           "--threads", "1", "--bandwidth", bw, "--latency", "10us", "--overhead", overhead, *extra]
    if fs:
        cmd += ["--fs-bandwidth", fs]
    r = subprocess.run(cmd, check=True, capture_output=True, text=True)
    return json.loads(r.stdout)


# The plot: speed-up over one node against nodes (log2 axis), a line per render and link.
W, H, PAD = 480, 320, 52
COLOURS = {"exact": "#1f77b4", "static": "#1f77b4", "ray caches": "#d62728", "hit maps": "#2ca02c", "dynamic": "#9467bd"}
DASHES = ["", "6,4", "2,3", "8,3,2,3"]


def plot(rows, nodes, links, dst, title):
    """rows: (render, link, n, speed-up); an SVG with no plotting library."""
    ymax = max(max(s for *_, s in rows), 1.0) * 1.1
    lmax = math.log2(max(nodes))

    def x(n):
        return PAD + math.log2(n) / max(lmax, 1) * (W - 2 * PAD)

    def y(s):
        return H - PAD - s / ymax * (H - 2 * PAD)

    out = [
        f'<svg xmlns="http://www.w3.org/2000/svg" width="{W}" height="{H}" font-family="sans-serif" font-size="11">',
        f'<rect width="{W}" height="{H}" fill="white"/>',
        f'<text x="{W / 2}" y="16" text-anchor="middle">{title}</text>',
        f'<line x1="{PAD}" y1="{H - PAD}" x2="{W - PAD}" y2="{H - PAD}" stroke="black"/>',
        f'<line x1="{PAD}" y1="{PAD}" x2="{PAD}" y2="{H - PAD}" stroke="black"/>',
        f'<text x="{W / 2}" y="{H - 12}" text-anchor="middle">nodes (one tracing thread each; log scale)</text>',
        f'<text x="14" y="{H / 2}" transform="rotate(-90 14 {H / 2})" text-anchor="middle">'
        'simulated speed-up over one node</text>',
    ]
    # The ideal (speed-up = nodes) up to the top of the plot.
    shown = [n for n in nodes if n <= ymax]
    ideal = " ".join(f"{x(n):.1f},{y(n):.1f}" for n in shown)
    out.append(f'<polyline points="{ideal}" fill="none" stroke="#999" stroke-dasharray="2,3"/>')
    out.append(f'<text x="{x(shown[-1]) + 4}" y="{y(shown[-1])}" fill="#999">ideal</text>')
    for n in nodes:
        out.append(f'<text x="{x(n)}" y="{H - PAD + 14}" text-anchor="middle">{n}</text>')
    step = max(1, round(ymax / 8))
    for k in range(0, int(ymax) + 1, step):
        out.append(f'<text x="{PAD - 6}" y="{y(k) + 4}" text-anchor="end">{k}</text>')
    legend = 0
    for render in COLOURS:
        for li, link in enumerate(links):
            pts = sorted((n, s) for r, l, n, s in rows if r == render and l == link)
            if not pts:
                continue
            dash = f' stroke-dasharray="{DASHES[li % len(DASHES)]}"' if DASHES[li % len(DASHES)] else ""
            p = " ".join(f"{x(n):.1f},{y(s):.1f}" for n, s in pts)
            out.append(f'<polyline points="{p}" fill="none" stroke="{COLOURS[render]}" stroke-width="2"{dash}/>')
            ly = PAD + 14 * legend
            out.append(f'<line x1="{PAD + 8}" y1="{ly - 4}" x2="{PAD + 36}" y2="{ly - 4}" '
                       f'stroke="{COLOURS[render]}" stroke-width="2"{dash}/>')
            out.append(f'<text x="{PAD + 42}" y="{ly}">{render}, {link}</text>')
            legend += 1
    out.append("</svg>")
    Path(dst).write_text("\n".join(out) + "\n")


def main():
    ap = argparse.ArgumentParser(prog="benches/sim/scaling.py")
    ap.add_argument("--job", choices=["cornell", "little", "bolstad", "navratil"], default="cornell",
                    help="cornell: cornell:glass in 64 domains (default); little: Table 5.1's bunny grid; "
                         "bolstad: hit maps on the Cornell box, path, 16 spp; navratil: the static schedule "
                         "against the dynamic one, loads from a shared file system, up to 1,024 nodes")
    ap.add_argument("--workers", type=int, help="workers of the recording (default: one per domain)")
    ap.add_argument("--nodes", help="node counts (default 1,2,...,64; little: 1,3,9,27)")
    ap.add_argument("--links", default="100Mbps,1Gbps,10Gbps")
    ap.add_argument("--fs-bandwidth", help="a shared file system for domain loads (e.g. 1GB/s)")
    ap.add_argument("--plot", help="write an SVG of the speed-ups (overhead modelled) here")
    ap.add_argument("--keep", help="record into this folder and keep the traces (replay them later with --from)")
    ap.add_argument("--from", dest="source",
                    help="replay the traces a --keep run left in this folder instead of rendering again")
    a = ap.parse_args()
    work = Path(a.source or a.keep or tempfile.mkdtemp(prefix="dray-scaling-"))
    work.mkdir(parents=True, exist_ok=True)
    job = {"little": lambda: little(work), "bolstad": bolstad, "cornell": cornell, "navratil": navratil}[a.job]()
    a.fs_bandwidth = a.fs_bandwidth or job.fs
    nodes = [int(x) for x in (a.nodes or job.nodes).split(",")]
    links = a.links.split(",")
    workers = a.workers or job.domains
    dray = str(REPO / "target" / "release" / "dray")
    rows = []
    recorded = {}
    first = "static" if job.replay_flags else "exact"
    for name, extra, rflags in [(first, [], []), (job.approx, job.caches, job.replay_flags)]:
        t = work / f"{name.replace(' ', '-')}.jsonl"
        if tuple(extra) in recorded:
            t = recorded[tuple(extra)]  # the same render: one recording, replayed two ways
        elif a.source:
            if not t.exists():
                raise SystemExit(f"--from {a.source}: no {t.name} (was it kept by `scaling.py --job {a.job} --keep`?)")
            recorded[tuple(extra)] = t
        else:
            subprocess.run([dray, "render", *job.flags, *extra, "-q", "--workers", str(workers),
                            "--output", str(t.with_suffix(".png")), "--trace-out", str(t)], check=True)
            recorded[tuple(extra)] = t
        for bw in links:
            base = {o: replay(t, 1, bw, o, a.fs_bandwidth, rflags)["makespan_s"] for o in ("model", "none")}
            for n in nodes:
                r = {o: replay(t, n, bw, o, a.fs_bandwidth, rflags) for o in ("model", "none")}
                rows.append((name, bw, n, r["model"]["makespan_s"], base["model"] / r["model"]["makespan_s"],
                             r["none"]["makespan_s"], base["none"] / r["none"]["makespan_s"],
                             r["model"]["bytes_sent"], r["model"]["messages"]))
    fs = f", loads from a {a.fs_bandwidth} file system" if a.fs_bandwidth else ""
    print(f"jobs: dray render {' '.join(job.flags)} [{' '.join(job.caches)}], recorded on {workers} workers{fs}")
    print()
    print("| render | link | nodes | simulated s | speed-up | overhead left out: s | speed-up | bytes between nodes "
          "| messages |")
    print("|---|---|---|---|---|---|---|---|---|")
    for name, bw, n, t, s, t_none, s_none, b, m in rows:
        print(f"| {name} | {bw} | {n} | {t:.3f} | {s:.2f} | {t_none:.3f} | {s_none:.2f} | {b} | {m} |")
    if a.plot:
        plot([(r[0], r[1], r[2], r[4]) for r in rows], nodes, links, a.plot, job.title + fs)
        print(f"\nplot: {a.plot}")


if __name__ == "__main__":
    main()
