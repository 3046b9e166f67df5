#!/usr/bin/env python3
"""Per-thread timeline of a `perf record` profile: where cores sit idle.

Buckets the samples of a `perf record -e cpu-clock` profile by thread and by time, and
prints one row per bucket: samples per thread (the busiest threads as columns) and the
two hottest symbols. At a sampling rate F, a busy thread shows F x bucket samples per
bucket; a thread with fewer is idle part of it. This is how the fourth pass on one node's
speed (docs/history/2026-11-24-one-node-speed.md, "Fourth pass") found a tracing thread
asleep while the other loaded the domain, and the serial build steps.

Usage:
    perf record -e cpu-clock -F 2000 -o OUT -- dray render SCENE ...
    python3 benches/perf_timeline.py OUT [--bucket 0.025] [--threads 6]
"""

from __future__ import annotations

import argparse
import collections
import subprocess
import sys


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("profile", help="perf.data file written by `perf record`")
    ap.add_argument("--bucket", type=float, default=0.025, help="bucket length in seconds (default 0.025)")
    ap.add_argument("--threads", type=int, default=6, help="thread columns to show (default 6)")
    args = ap.parse_args()
    try:
        out = subprocess.run(
            ["perf", "script", "-i", args.profile, "-F", "tid,time,ip,sym"],
            capture_output=True, text=True, check=True,
        ).stdout
    except FileNotFoundError:
        sys.exit("perf is not installed (Debian: linux-perf)")
    except subprocess.CalledProcessError as e:
        sys.exit(f"perf script failed on {args.profile}: {e.stderr.strip()}")
    rows = []
    for line in out.splitlines():
        parts = line.split(None, 3)
        if len(parts) < 2:
            continue
        try:
            tid, t = int(parts[0]), float(parts[1].rstrip(":"))
        except ValueError:
            continue
        sym = parts[3] if len(parts) > 3 else "?"
        rows.append((tid, t, sym))
    if not rows:
        sys.exit(f"no samples in {args.profile}")
    t0 = min(r[1] for r in rows)
    span = max(r[1] for r in rows) - t0
    buckets = int(span / args.bucket) + 1
    per_thread: dict[int, list[int]] = collections.defaultdict(lambda: [0] * buckets)
    hottest: dict[int, collections.Counter] = collections.defaultdict(collections.Counter)
    for tid, t, sym in rows:
        b = int((t - t0) / args.bucket)
        per_thread[tid][b] += 1
        hottest[b][sym.split("<")[0][:60]] += 1
    tids = sorted(per_thread, key=lambda k: -sum(per_thread[k]))[: args.threads]
    print(f"span {span:.3f} s, {len(rows)} samples, bucket {args.bucket} s")
    print("start (s) " + " ".join(f"{t:>7}" for t in tids) + "   hottest symbols")
    for b in range(buckets):
        top = "; ".join(f"{s} {n}" for s, n in hottest[b].most_common(2))
        print(f"{b * args.bucket:9.3f} " + " ".join(f"{per_thread[t][b]:>7}" for t in tids) + f"   {top}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
