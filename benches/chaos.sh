#!/usr/bin/env bash
# The chaos test (cli/tests/chaos.rs) at length: short jobs of random shapes over a
# real cluster (a coordinator on a state directory and 3 workers) while workers are
# SIGKILLed and restarted on their ports, SIGSTOPped and continued, and the coordinator
# is SIGKILLed and started again on its state directory. Every job must end SUCCEEDED
# with `dray render --workers 0`'s bits or FAILED with a reason; the test fails on a
# hang or a wrong image and prints the seed that replays it. The last line is the
# counts (jobs, kills, stops, coordinator restarts, hangs, wrong images, seconds).
#
# Usage: benches/chaos.sh [--long] [--jobs N] [--seed S]
#   default: the test's own job count (40, what CI runs); --long: 300 jobs.
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."
jobs=""
while [ $# -gt 0 ]; do
    case "$1" in
        --long) jobs=300 ;;
        --jobs) jobs="$2"; shift ;;
        --seed) export DRAY_CHAOS_SEED="$2"; shift ;;
        -h|--help) sed -n '2,12p' "$0"; exit 0 ;;
        *) echo "benches/chaos.sh: unknown argument $1" >&2; exit 2 ;;
    esac
    shift
done
if [ -n "$jobs" ]; then
    export DRAY_CHAOS_JOBS="$jobs"
fi
log=$(mktemp)
trap 'rm -f "$log"' EXIT
start=$SECONDS
set +e
nice cargo test --release -p dray --test chaos -- --nocapture 2>&1 | tee "$log" \
    | grep --line-buffered -E '^chaos: (seed [0-9]+ \(|job [0-9]+ .*(SUCCEEDED|FAILED|WRONG|HANG|ENDED))'
status=${PIPESTATUS[0]}
set -e
echo "benches/chaos.sh: exit $status, $((SECONDS - start)) s wall including the build"
grep -E '^chaos: seed [0-9]+: ' "$log" | tail -1
exit "$status"
