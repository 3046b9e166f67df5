#!/usr/bin/env bash
# Build the dray binary (unless DRAY_BIN is set), then run benches/scheduling.py (the
# scheduling experiment: image-plane, domain and dynamic schedules on a scene larger than a
# worker's memory budget; docs/benchmarks.md, "Scheduling"). Standard-library Python, plus
# matplotlib in the benchmark venv for --plot.
# Usage: benches/scheduling.sh [options of scheduling.py]   (see: python3 benches/scheduling.py --help)
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."
if [ -z "${DRAY_BIN:-}" ]; then
    cargo build --release -p dray
fi
exec python3 benches/scheduling.py "$@"
