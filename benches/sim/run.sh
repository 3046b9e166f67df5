#!/usr/bin/env bash
# Run a script of benches/sim with SimGrid importable (fetched by setup.sh when needed):
#   benches/sim/run.sh replay.py TRACE [options]
set -euo pipefail
here="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
envs="$("$here/setup.sh")"
eval "$envs"
script="$1"
shift
exec "${DRAY_SIM_PYTHON:-python3}" "$here/$script" "$@"
