#!/usr/bin/env bash
# Build dray's fuzz targets with cargo-fuzz and run each for a while, one after another,
# on one core. Used by .ci/run (a short smoke run) and for the long runs recorded in
# docs/fuzzing.md.
#
#   fuzz/run.sh [--seconds N] [--keep-going] [--no-build] [TARGET...]
#
# --seconds N    libFuzzer's -max_total_time per target (default 20)
# --keep-going   after a crash, keep the artifact and fuzz on for the rest of the time
#                (the long runs); without it the first crash ends that target (CI)
# --no-build     use the binaries already in fuzz/target
# TARGET...      default: every target in fuzz/fuzz_targets
#
# Seeds are read from fuzz/corpus/<target>/ and never written: what a run finds goes to
# fuzz/work/<target>/ (ignored by git), crash/timeout/OOM inputs to
# fuzz/artifacts/<target>/, logs to fuzz/work/logs/<target>.log. Each target gets
# -rss_limit_mb=2048, -timeout=10 (an input taking longer is a finding) and its
# dictionary from fuzz/dicts/ when there is one. Exits non-zero when any target crashed,
# timed out or ran out of memory. Needs cargo-fuzz and RUSTC_BOOTSTRAP=1 (set here),
# since cargo-fuzz passes nightly flags to the stable compiler.
set -euo pipefail
cd "$(dirname "$0")"

seconds=20
keep_going=0
build=1
targets=()
while [ $# -gt 0 ]; do
  case "$1" in
    --seconds) seconds=$2; shift 2 ;;
    --keep-going) keep_going=1; shift ;;
    --no-build) build=0; shift ;;
    -h|--help) sed -n '2,21p' "$0"; exit 0 ;;
    -*) echo "fuzz/run.sh: unknown option $1" >&2; exit 2 ;;
    *) targets+=("$1"); shift ;;
  esac
done
all_targets=0
if [ ${#targets[@]} -eq 0 ]; then
  all_targets=1
  for f in fuzz_targets/*.rs; do targets+=("$(basename "$f" .rs)"); done
fi

export RUSTC_BOOTSTRAP=1
export CARGO_BUILD_JOBS="${CARGO_BUILD_JOBS:-1}"
triple=$(rustc -vV | sed -n 's/^host: //p')
bin_dir="target/$triple/release"

if [ "$build" -eq 1 ]; then
  echo "fuzz/run.sh: building ${targets[*]} (cargo fuzz build, ASan, release + debug assertions)"
  build_start=$SECONDS
  if [ "$all_targets" -eq 1 ]; then
    cargo fuzz build
  else
    for t in "${targets[@]}"; do
      cargo fuzz build "$t"
    done
  fi
  echo "fuzz/run.sh: build took $((SECONDS - build_start)) s"
fi

# The meshopt crate (glTF's EXT_meshopt_compression) links meshoptimizer's C++ sources
# so that one constant table ('edges' in opacitymap.cpp) is registered twice with the
# same size; ASan's strictest ODR check (level 2, its default) aborts every run on that
# at start. Level 1 still reports globals defined twice with different sizes, the
# violations that corrupt memory.
export ASAN_OPTIONS="${ASAN_OPTIONS:+$ASAN_OPTIONS:}detect_odr_violation=1"

mkdir -p work/logs
failed=()
for t in "${targets[@]}"; do
  bin="$bin_dir/$t"
  if [ ! -x "$bin" ]; then
    echo "fuzz/run.sh: $bin is missing (build first)" >&2
    exit 2
  fi
  mkdir -p "work/$t" "artifacts/$t"
  args=(-max_total_time="$seconds" -rss_limit_mb=2048 -timeout=10 -print_final_stats=1
        -artifact_prefix="artifacts/$t/")
  if [ -f "dicts/$t.dict" ]; then args+=(-dict="dicts/$t.dict"); fi
  log="work/logs/$t.log"
  : >"$log"
  start=$SECONDS
  crashes=0
  runs=0
  while :; do
    left=$((seconds - (SECONDS - start)))
    [ "$left" -ge 1 ] || break
    args[0]=-max_total_time=$left
    runs=$((runs + 1))
    echo "fuzz/run.sh: [$t] $bin ${args[*]} work/$t corpus/$t" >>"$log"
    set +e
    "$bin" "${args[@]}" "work/$t" "corpus/$t" >>"$log" 2>&1
    rc=$?
    set -e
    [ "$rc" -eq 0 ] && break
    crashes=$((crashes + 1))
    if [ "$keep_going" -eq 0 ] || [ "$runs" -ge 20 ]; then break; fi
  done
  execs=$(grep -Eo 'stat::number_of_executed_units: [0-9]+' "$log" | awk '{s+=$2} END {print s+0}')
  cov=$(grep -Eo 'cov: [0-9]+' "$log" | tail -1 | awk '{print $2}')
  ft=$(grep -Eo 'ft: [0-9]+' "$log" | tail -1 | awk '{print $2}')
  corpus=$(find "work/$t" -type f | wc -l)
  contained=$(grep -c '^dray-fuzz: contained panic' "$log" || true)
  summary="[$t] $((SECONDS - start)) s, ${execs} execs, cov ${cov:-?} ft ${ft:-?}, corpus ${corpus} files, contained panics ${contained}"
  if [ "$crashes" -gt 0 ]; then
    echo "fuzz/run.sh: $summary: FAILED ($crashes crash/timeout/OOM; artifacts in fuzz/artifacts/$t/, log fuzz/$log)"
    grep -E '^(==[0-9]+==ERROR|SUMMARY|thread .* panicked|dray-fuzz: contained|artifact_prefix|Test unit written)' "$log" | head -20 | sed 's/^/    /'
    failed+=("$t")
  else
    echo "fuzz/run.sh: $summary: ok"
  fi
done

if [ ${#failed[@]} -gt 0 ]; then
  echo "fuzz/run.sh: crashes in: ${failed[*]}"
  exit 1
fi
echo "fuzz/run.sh: all ${#targets[@]} targets ran ${seconds} s each without a crash"
