#!/usr/bin/env bash
# A Python venv holding pinned requirements, for the test scripts (tests/helm/check.sh,
# tests/browser/run.sh):
#
#   tests/venv.sh REQUIREMENTS VENV WHO
#
# (re)builds VENV from REQUIREMENTS only when the file changed since the last build (its
# SHA-256 is kept in VENV/.requirements.sha256), quietly unless pip fails; WHO names the
# caller in messages. Exits non-zero when python3 is missing or pip fails.
set -euo pipefail
req=$1 venv=$2 who=$3
stamp="$venv/.requirements.sha256"
want=$(sha256sum "$req" | cut -d' ' -f1)
if [ -x "$venv/bin/python" ] && [ "$(cat "$stamp" 2>/dev/null)" = "$want" ]; then
  exit 0
fi
if ! command -v python3 >/dev/null 2>&1; then
  echo "$who: FAILED: python3 is required" >&2
  exit 1
fi
echo "$who: installing $req into $venv"
mkdir -p "$(dirname "$venv")"
python3 -m venv --clear "$venv"
log=$(mktemp)
if ! "$venv/bin/python" -m pip install --quiet --disable-pip-version-check \
    --no-input -r "$req" >"$log" 2>&1; then
  cat "$log" >&2
  rm -f "$log"
  echo "$who: FAILED: pip could not install $req (is the package index reachable?)" >&2
  exit 1
fi
rm -f "$log"
echo "$want" >"$stamp"
