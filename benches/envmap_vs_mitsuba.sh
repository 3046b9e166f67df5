#!/usr/bin/env bash
# Build the dray binary (unless DRAY_BIN is set), then run benches/envmap_vs_mitsuba.py, which creates
# benches/.venv and installs benches/requirements.txt into it on first use.
# Usage: benches/envmap_vs_mitsuba.sh [options of envmap_vs_mitsuba.py]   (see: python3 benches/envmap_vs_mitsuba.py --help)
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."
if [ -z "${DRAY_BIN:-}" ]; then
    cargo build --release -p dray
fi
exec python3 benches/envmap_vs_mitsuba.py "$@"
