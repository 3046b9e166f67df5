#!/usr/bin/env bash
# Build the dray binary (unless DRAY_BIN is set), then run benches/ray_throughput.py, which creates
# benches/.venv and installs benches/requirements.txt into it on first use.
# Usage: benches/ray_throughput.sh [options of ray_throughput.py]   (see: python3 benches/ray_throughput.py --help)
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."
if [ -z "${DRAY_BIN:-}" ]; then
    cargo build --release -p dray
fi
exec python3 benches/ray_throughput.py "$@"
