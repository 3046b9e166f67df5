#!/usr/bin/env bash
# A billion triangles out of core (docs/benchmarks.md; notes to come in docs/history/): builds the
# dray binary (unless DRAY_BIN is set), then runs benches/billion.py, which partitions
# grid:iso:gyroid:648:5x5x5 (1.02 billion triangles, a package of about 46 GB) into 1024 kd
# domains on disk and renders it at 512x512, 1 spp (whitted) on `dray cluster --workers 4`
# with 2 GiB memory budgets and the dynamic schedule, recording partition time, disk, peak
# RSS of every process, domain loads and evictions, wall time and the image.
# Takes about an hour on the project's 2-core, 24 GiB machine (more when the cores are
# shared) and needs about 52 GB free under --work; a benchmark, never run in CI.
# `--quick` does the same on 20 million triangles in a few minutes.
# Usage: benches/billion.sh [options of billion.py]   (see: python3 benches/billion.py --help)
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."
if [ -z "${DRAY_BIN:-}" ]; then
    cargo build --release -p dray
fi
exec python3 benches/billion.py "$@"
