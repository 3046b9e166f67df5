#!/usr/bin/env python3
"""Validate benches/sim/replay.py against real runs on this machine (docs/caches.md
"Simulation at scale: validation").

For each worker count N: ROUNDS renders of one job with `dray render --workers N
--trace-out`, measured by the job's wall time (the trace's `job` line); the trace of the
first round is replayed on one host of this machine's cores (`--one-host`) and its
prediction compared with the median of the other rounds (so the trace replayed is not
the run it is judged against). Then the trace recorded at the largest N is replayed at
every other N (domains re-dealt), against those N's medians.

    benches/sim/run.sh validate.py [--workers 2,4,8] [--rounds 5] [--keep DIR] [-- render flags]
    benches/sim/run.sh validate.py --from DIR     # the kept runs, replayed again
    benches/sim/run.sh validate.py --link bandwidth=100mbit,latency=1ms --workers 2 [...]

`--link SPEC` records on a local `dray cluster --workers N --threads 1 --emulate-link SPEC
--trace-dir ...` instead (worker processes talking gRPC through emulated links, one
`dray submit --trace` per round after an untraced warm-up job), joins each job's
per-worker files into one trace whose `job` line holds the workers' busy span as the
measured time (the cluster has no single clock; every worker's times start at its own
set-up of the job), and replays it on N nodes behind links of SPEC's bandwidth and
latency that compute on one host of this machine's cores (`--one-host --topology pairs`,
as the cluster's worker processes share them; `--link-cores own` gives each node a core
of its own instead, the model before 2026-11-30) (`--overhead model`, `--network-model CM02`: a message takes the
latency plus its size over the bandwidth, as the emulation shapes it; SimGrid's default
LV08 adds TCP's factors, which a real cluster has and the emulation does not; `--topology
pairs`: a link per ordered pair of nodes, as the emulation shapes each connection on its
own, where a cluster's node has one NIC for all its peers, replay.py's default `star`). This checks the replay's links against the
emulated ones.

Prints a Markdown table: N, the measured median (and the spread of the rounds), the
replays of its own traces, of the largest N's traces, the errors, and the share of the
cores that other processes left the render (/proc/stat's busy time over each round, less
the render's own CPU): near 1 the machine was quiet and the comparison means something.
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


REPLAY_ARGS = []
# "--one-host" for runs recorded in one process; the links' flags for `--link` runs.
PLACEMENT_ARGS = ["--one-host"]


def link_args(spec):
    """replay.py's --bandwidth and --latency for an `--emulate-link` SPEC."""
    args = []
    for part in filter(None, (p.strip() for p in spec.split(","))):
        key, _, value = part.partition("=")
        if key == "bandwidth":
            args += ["--bandwidth", value]
        elif key == "latency":
            args += ["--latency", value]
        else:
            raise SystemExit(f"--link {spec!r}: unknown key {key!r} (bandwidth, latency)")
    if "--bandwidth" not in args:
        raise SystemExit(f"--link {spec!r}: give a bandwidth (the replay's links need one)")
    return args


class LinkCluster:
    """A local `dray cluster` of N single-thread workers behind emulated links, writing
    the traces of jobs submitted with `--trace` into its own folder."""

    def __init__(self, n, spec, work, port):
        sys.path.insert(0, str(REPO / "benches"))
        import _bench_env as env
        self.traces = work / f"cluster-n{n}-traces"
        self.traces.mkdir(parents=True, exist_ok=True)
        self.cluster = env.Cluster(Path(dray()), n, port, work, work / f"cluster-n{n}.log",
                                   ["--threads", "1", "--emulate-link", spec, "--trace-dir", str(self.traces)])
        self.addr = self.cluster.addr

    def submit(self, job, out, trace):
        cmd = [dray(), "submit", "--coordinator", self.addr, "-q", *job, "--output", str(out)]
        if trace:
            cmd.insert(2, "--trace")
        subprocess.run(cmd, check=True)

    def stop(self):
        self.cluster.stop()


def record_on_cluster(cluster, n, job, out):
    """One traced job on `cluster`: its per-worker files joined into `out` after a `job`
    line whose wall time is the workers' busy span (the latest step's end, each worker's
    clock starting at its set-up of the job)."""
    before = set(cluster.traces.glob("*.jsonl"))
    b0 = busy_seconds()
    cluster.submit(job, out.with_suffix(".png"), trace=True)
    b1 = busy_seconds()
    # A worker writes its trace when the job ends on it: wait for every worker's file and
    # for the files to stop growing.
    import time
    files, sizes = [], None
    for _ in range(200):
        files = sorted(set(cluster.traces.glob("*.jsonl")) - before)
        now = [f.stat().st_size for f in files]
        if len(files) >= n and now == sizes:
            break
        sizes = now
        time.sleep(0.1)
    if len(files) < n:
        raise SystemExit(f"{n} workers but {len(files)} trace files in {cluster.traces} for one job")
    records = []
    for f in files:
        records += [json.loads(line) for line in f.read_text().splitlines() if line.strip()]
    span = max((r["t1"] for r in records if r.get("rec") in ("step", "load")), default=0)
    cores = os.cpu_count()
    head = {"v": records[0]["v"], "rec": "job", "wall_ns": span, "workers": n, "threads": 1, "cores": cores,
            "job": job, "recorded_on": "dray cluster", "stats": {}}
    with open(out, "w") as w:
        w.write(json.dumps(head) + "\n")
        for r in records:
            w.write(json.dumps(r) + "\n")
    wall = span / 1e9
    span_cores = max(wall, 1e-9) * cores
    others = max(0.0, (b1 - b0) - sum(r["cpu_ns"] for r in records if "cpu_ns" in r) / 1e9)
    return wall, max(0.05, (span_cores - others) / span_cores)


def replay(trace, *args):
    r = subprocess.run([sys.executable, str(HERE / "replay.py"), str(trace), "--json", *PLACEMENT_ARGS, *REPLAY_ARGS, *args],
                       check=True, capture_output=True, text=True)
    return json.loads(r.stdout)


def main():
    ap = argparse.ArgumentParser(prog="benches/sim/validate.py")
    ap.add_argument("--workers", default="2,4,8")
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--keep", help="record into this folder and keep it (walls.json beside the traces)")
    ap.add_argument("--from", dest="source",
                    help="replay a folder kept by --keep instead of rendering (the model changes, the runs do not)")
    ap.add_argument("job", nargs="*", help="dray render's scene and flags (default: %s)" % " ".join(DEFAULT_JOB))
    ap.add_argument("--replay-args", default="", help="more flags for replay.py (e.g. \"--overhead-on thread\")")
    ap.add_argument("--link", metavar="SPEC",
                    help="record on a local dray cluster behind --emulate-link SPEC (e.g. bandwidth=100mbit,latency=1ms)")
    ap.add_argument("--port", type=int, default=52100, help="--link: the clusters' first port")
    ap.add_argument("--link-cores", choices=["shared", "own"], default="shared",
                    help="--link: the replay's nodes compute on one host of this machine's cores (shared, "
                         "as the cluster's processes do) or on a core each (own)")
    a = ap.parse_args()
    REPLAY_ARGS.extend(a.replay_args.split())
    job = a.job or DEFAULT_JOB
    ns = [int(x) for x in a.workers.split(",")]
    if a.rounds < 2:
        raise SystemExit("--rounds: at least 2 (one to replay, the others to judge it by)")
    walls, free, traces = {}, {}, {}
    if a.source:
        work = Path(a.source)
        kept = json.loads((work / "walls.json").read_text())
        job, ns = kept["job"], [int(n) for n in kept["walls"]]
        a.link = kept.get("link")
        for n in ns:
            walls[n], free[n] = kept["walls"][str(n)], kept["free"][str(n)]
            traces[n] = [work / f"n{n}-r{r}.jsonl" for r in range(len(walls[n]))]
    else:
        work = Path(a.keep) if a.keep else Path(tempfile.mkdtemp(prefix="dray-validate-"))
        work.mkdir(parents=True, exist_ok=True)
        if a.link:
            # One cluster per N, kept for its rounds (after an untraced warm-up job, so
            # that every traced round finds its domains loaded alike).
            for i, n in enumerate(ns):
                cluster = LinkCluster(n, a.link, work, a.port + 10 * i)
                try:
                    cluster.submit(job, work / f"n{n}-warm.png", trace=False)
                    for r in range(a.rounds):
                        t = work / f"n{n}-r{r}.jsonl"
                        wall, share = record_on_cluster(cluster, n, job, t)
                        walls.setdefault(n, []).append(wall)
                        free.setdefault(n, []).append(share)
                        traces.setdefault(n, []).append(t)
                finally:
                    cluster.stop()
        else:
            # Rounds interleaved across N, so that a change in the machine's load meanwhile
            # touches every N alike.
            for r in range(a.rounds):
                for n in ns:
                    t = work / f"n{n}-r{r}.jsonl"
                    wall, share = record(n, job, t)
                    walls.setdefault(n, []).append(wall)
                    free.setdefault(n, []).append(share)
                    traces.setdefault(n, []).append(t)
        (work / "walls.json").write_text(json.dumps({"job": job, "walls": walls, "free": free, "link": a.link}))
    if a.link:
        PLACEMENT_ARGS[:] = link_args(a.link) + ["--threads", "1", "--overhead", "model", "--network-model", "CM02",
                                               "--topology", "pairs"]
        if a.link_cores == "shared":
            # The machine's cores (the trace's `job` line: os.cpu_count() when recorded).
            PLACEMENT_ARGS.append("--one-host")
    big = max(ns)
    rows = []
    pct = lambda p, m: 100 * (p - m) / m
    for n in ns:
        w = walls[n]
        # Every round's trace replayed, each judged by the median of the other rounds
        # (never by the run it was recorded in); and, as a check of the model alone,
        # by its own run.
        own = [replay(t) for t in traces[n]]
        loo = [pct(o["predicted_s"], statistics.median(w[:r] + w[r + 1:])) for r, o in enumerate(own)]
        self_err = [pct(o["predicted_s"], o["measured_s"]) for o in own]
        cross = [replay(t, "--nodes", str(n)) for t in traces[big]] if n != big else own
        cross_p = statistics.median(c["predicted_s"] for c in cross)
        rows.append((n, statistics.median(w), min(w), max(w),
                     statistics.median(o["predicted_s"] for o in own), min(o["predicted_s"] for o in own),
                     max(o["predicted_s"] for o in own), statistics.median(loo), max(loo, key=abs),
                     statistics.median(self_err), cross_p, pct(cross_p, statistics.median(w)),
                     statistics.median(free[n])))
    how = (f"dray submit to dray cluster --workers N --threads 1 --emulate-link {a.link} (replay: cores "
           f"{a.link_cores})") if a.link else "dray render --workers N"
    print(f"job: {' '.join(job)} by {how}; {len(walls[ns[0]])} rounds; machine cores: {os.cpu_count()}; "
          f"replay flags: {' '.join(REPLAY_ARGS) or 'defaults'}")
    print()
    print("| workers | measured median (min-max), s | replayed, each round's trace: median (min-max), s | "
          "error against the other rounds: median (worst) | against its own run: median | "
          f"{big}-worker traces re-dealt: median, s | error | cores left by others |")
    print("|---|---|---|---|---|---|---|---|")
    for n, med, lo, hi, p, plo, phi, e, worst, own_e, cross_p, cross_e, share in rows:
        print(f"| {n} | {med:.3f} ({lo:.3f}-{hi:.3f}) | {p:.3f} ({plo:.3f}-{phi:.3f}) | {e:+.0f}% ({worst:+.0f}%) | "
              f"{own_e:+.0f}% | {cross_p:.3f} | {cross_e:+.0f}% | {share:.2f} |")

if __name__ == "__main__":
    main()
