#!/usr/bin/env bash
# The web dashboard in a real browser (tests/browser/dashboard_test.py): headless
# Chromium from Debian's packages, driven over WebDriver by Python Selenium, against a
# real `dray cluster --workers 2 --http-listen ...`. Screenshots go to
# target/browser-artifacts/.
#
#   tests/browser/run.sh          # from anywhere; exits non-zero on any failure
#
# - Chromium: `chromium` and `chromium-driver` are installed with apt-get when missing
#   and this runs as root (CI does). Without them the test says so loudly and fails
#   when CI=true; elsewhere it prints "browser test: SKIPPED" and passes.
# - Python: tests/browser/requirements.txt (pinned) in target/browser-venv, rebuilt
#   only when the requirements change.
# - dray: target/release/dray (DRAY_BIN overrides), built with cargo when missing.
set -euo pipefail
cd "$(dirname "$0")/../.."

say() { echo "tests/browser/run.sh: $*"; }

if ! command -v chromium >/dev/null 2>&1 || ! command -v chromedriver >/dev/null 2>&1; then
  if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then
    say "installing chromium and chromium-driver from Debian's packages"
    apt_log=$(mktemp)
    if ! { apt-get update -qq && DEBIAN_FRONTEND=noninteractive \
        apt-get install -y -qq --no-install-recommends chromium chromium-driver; } \
        >"$apt_log" 2>&1; then
      tail -20 "$apt_log" >&2
    fi
    rm -f "$apt_log"
  fi
fi
if ! command -v chromium >/dev/null 2>&1 || ! command -v chromedriver >/dev/null 2>&1; then
  echo "############################################################################" >&2
  echo "## browser test: NO CHROMIUM: chromium and chromedriver are not installed  ##" >&2
  echo "## (apt-get install -y chromium chromium-driver, as root); the dashboard   ##" >&2
  echo "## was NOT tested in a browser.                                            ##" >&2
  echo "############################################################################" >&2
  if [ "${CI:-}" = "true" ]; then
    echo "browser test: FAILED (no Chromium, and CI=true)" >&2
    exit 1
  fi
  echo "browser test: SKIPPED (no Chromium)"
  exit 0
fi

venv=target/browser-venv
if ! tests/venv.sh tests/browser/requirements.txt "$venv" tests/browser/run.sh; then
  echo "browser test: FAILED: its Python packages could not be installed" >&2
  exit 1
fi

dray="${DRAY_BIN:-target/release/dray}"
if [ ! -x "$dray" ]; then
  say "building $dray"
  cargo build --release -p dray
fi

# Selenium Manager is never needed (the driver's path is given): no statistics either.
export SE_AVOID_STATS=true
exec "$venv/bin/python" tests/browser/dashboard_test.py --dray "$dray" \
  --grpcurl "$venv/bin/grpcurl" --artifacts target/browser-artifacts "$@"
