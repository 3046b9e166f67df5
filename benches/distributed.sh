#!/usr/bin/env bash
# Build the dray binary (unless DRAY_BIN is set), then run benches/distributed.py (the
# distributed runtime's benchmarks, docs/benchmarks.md "Distributed runtime": overhead of
# distribution, one ray stream on loopback, a 10M+-triangle scene in 64 domains on 4
# workers, partitioning 100M triangles). Standard-library Python only;
# GetJob statistics are read with the grpcio venv that .ci/run builds (target/py-venv).
# Usage: benches/distributed.sh [options of distributed.py]   (see: python3 benches/distributed.py --help)
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."
if [ -z "${DRAY_BIN:-}" ]; then
    cargo build --release -p dray
fi
exec python3 benches/distributed.py "$@"
