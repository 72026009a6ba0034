#!/usr/bin/env bash
# The main job, end to end on the embedded synthetic data (extra arguments go to the job).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
exec .venv/bin/python scripts/main.py "$@"
