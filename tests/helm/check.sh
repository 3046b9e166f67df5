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

venv=target/helm-venv
tests/venv.sh tests/helm/requirements.txt "$venv" tests/helm/check.sh

exec "$venv/bin/python" tests/helm/check_chart.py \
  --kubernetes-validate "$venv/bin/kubernetes-validate" "$@"
