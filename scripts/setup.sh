#!/usr/bin/env bash
# Creates .venv inside the checkout and installs the project into it (idempotent).
# torch==2.13.0 is installed first when missing, so that the CPU build is used and the
# package's open torch range adds nothing.
set -euo pipefail
cd "$(dirname "$0")/.."
PYTHON=${PYTHON:-python3}
if [ ! -x .venv/bin/python ]; then
  echo "[setup] creating .venv"
  "$PYTHON" -m venv .venv
fi
PY=.venv/bin/python
stamp=.venv/.evflow-installed
want="$(cat pyproject.toml | sha256sum | cut -c1-16)"
if [ -f "$stamp" ] && [ "$(cat "$stamp")" = "$want" ]; then
  exit 0
fi
if ! "$PY" -c "import torch" >/dev/null 2>&1; then
  echo "[setup] installing torch==2.13.0"
  "$PY" -m pip install --quiet --disable-pip-version-check torch==2.13.0
fi
echo "[setup] installing the project and its test extras"
"$PY" -m pip install --quiet --disable-pip-version-check -e ".[test,dsec,tonic]"
echo "$want" > "$stamp"
