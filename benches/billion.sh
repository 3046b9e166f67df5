#!/usr/bin/env bash
# A billion triangles out of core (docs/history/2026-11-26-billion-triangles.md): builds the
# dray binary (unless DRAY_BIN is set), then runs benches/billion.py, which partitions
# grid:iso:gyroid:648:5x5x5 (1.02 billion triangles, a package of 33 GB) into 1024 kd
# domains on disk and renders it at 512x512, 1 spp (whitted) on `dray cluster --workers 4`
# with 2 GiB memory budgets and the dynamic schedule, recording partition time, disk, peak
# RSS of every process, domain loads and evictions, wall time and the image.
# Took 35 minutes on the project's 2-core, 24 GiB machine (17 to partition, 18 to render,
# with other builds on the cores) and needs about 40 GB free under --work (default
# benches/out/billion; the package is deleted at the end). A benchmark, never run in CI.
# `--quick` does the same on 20 million triangles in about two minutes.
# Usage: benches/billion.sh [options of billion.py]   (see: python3 benches/billion.py --help)
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."
if [ -z "${DRAY_BIN:-}" ]; then
    cargo build --release -p dray
fi
exec python3 benches/billion.py "$@"
