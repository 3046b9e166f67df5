#!/usr/bin/env bash
# Build the dray binary (unless DRAY_BIN is set), then run benches/caches.py (Little 2011's
# Table 5.1: ray caches on a 3x3x3 bunny grid, with dray sweep; docs/caches.md, and
# docs/benchmarks.md, "Ray caches").
# Standard-library Python only. Usage: benches/caches.sh [options of caches.py]
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."
if [ -z "${DRAY_BIN:-}" ]; then
    cargo build --release -p dray
fi
exec python3 benches/caches.py "$@"
