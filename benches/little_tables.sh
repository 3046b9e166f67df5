#!/usr/bin/env bash
# Build the dray binary (unless DRAY_BIN is set), then run benches/little_tables.py
# (Little 2011's Tables 5.1-5.7 set-up with the faithful modes of issue 43: the `primary`
# integrator, randomized coarse positions, caches filled during the render, the 5x5x5
# grid and coarse passes of 256^2-512^2; docs/caches.md "Little's tables, faithful modes").
# Standard-library Python only. Usage: benches/little_tables.sh [options of little_tables.py]
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."
if [ -z "${DRAY_BIN:-}" ]; then
    nice -n 10 cargo build --release -p dray
fi
exec python3 benches/little_tables.py "$@"
