#!/usr/bin/env python
"""Evaluate models and baselines on recordings and benchmark protocols (evflow_cli/commands/evaluate.py; console command evflow-evaluate)."""
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from evflow_cli.commands.cli import run  # noqa: E402  (a user error: one line, exit 2)
from evflow_cli.commands.evaluate import main  # noqa: E402

if __name__ == "__main__":
    sys.exit(run(main))
