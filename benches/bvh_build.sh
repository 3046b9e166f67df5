#!/usr/bin/env bash
# Build the dray binary (unless DRAY_BIN is set), then run benches/bvh_build.py, which creates
# benches/.venv and installs benches/requirements.txt into it on first use.
# Usage: benches/bvh_build.sh [options of bvh_build.py]   (see: python3 benches/bvh_build.py --help)
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."
if [ -z "${DRAY_BIN:-}" ]; then
    cargo build --release -p dray
fi
exec python3 benches/bvh_build.py "$@"
