#!/usr/bin/env python
"""Predict flow for a recording with a trained or shipped model (evflow_cli/commands/predict.py; console command evflow-predict)."""
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from evflow_cli.commands.cli import run  # noqa: E402  (a user error: one line, exit 2)
from evflow_cli.commands.predict import main  # noqa: E402

if __name__ == "__main__":
    sys.exit(run(main))
