#!/usr/bin/env python
"""Accuracy against time per window: network, network + short solve, model-free solve (evflow_cli/commands/tradeoff.py)."""
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from evflow_cli.commands.cli import run  # noqa: E402  (a user error: one line, exit 2)
from evflow_cli.commands.tradeoff import main  # noqa: E402

if __name__ == "__main__":
    sys.exit(run(main))
