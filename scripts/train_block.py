#!/usr/bin/env python
"""Train the learned finish: a small update block that finishes the network's proposals (evflow_cli/commands/train_block.py)."""
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from evflow_cli.commands.cli import run  # noqa: E402  (a user error: one line, exit 2)
from evflow_cli.commands.train_block import main  # noqa: E402

if __name__ == "__main__":
    sys.exit(run(main))
