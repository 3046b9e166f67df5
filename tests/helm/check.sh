#!/usr/bin/env bash
# The helm/dray chart checked with the real tools: Helm's own engine (PyPI helm-python-sdk,
# Helm v4's Go SDK) lints it strictly and renders it for default and non-default values,
# and every rendered manifest must pass `kubernetes-validate --strict -k 1.30.0`
# (tests/helm/check_chart.py says what else it checks). No cluster is needed.
#
#   tests/helm/check.sh            # from anywhere; exits non-zero on any failure
#
# The tools are installed from tests/helm/requirements.txt (pinned) into target/helm-venv,
# rebuilt only when the requirements change. If pip cannot install them, this fails.
# Rendered manifests are left in target/helm-rendered/ for inspection.
set -euo pipefail
cd "$(dirname "$0")/../.."

req=tests/helm/requirements.txt
venv=target/helm-venv
stamp="$venv/.requirements.sha256"
want=$(sha256sum "$req" | cut -d' ' -f1)
if [ ! -x "$venv/bin/python" ] || [ "$(cat "$stamp" 2>/dev/null)" != "$want" ]; then
  if ! command -v python3 >/dev/null 2>&1; then
    echo "tests/helm/check.sh: FAILED: python3 is required" >&2
    exit 1
  fi
  echo "tests/helm/check.sh: installing $req into $venv"
  mkdir -p target
  python3 -m venv --clear "$venv"
  log=$(mktemp)
  if ! "$venv/bin/python" -m pip install --quiet --disable-pip-version-check \
      --no-input -r "$req" >"$log" 2>&1; then
    cat "$log" >&2
    rm -f "$log"
    echo "tests/helm/check.sh: FAILED: pip could not install $req (is the package index reachable?)" >&2
    exit 1
  fi
  rm -f "$log"
  echo "$want" >"$stamp"
fi

exec "$venv/bin/python" tests/helm/check_chart.py \
  --kubernetes-validate "$venv/bin/kubernetes-validate" "$@"
