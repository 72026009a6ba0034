#!/usr/bin/env python
"""A long training run that survives sessions: train in chunks, validate after each, and ship (evflow_cli/commands/ship.py)."""
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from evflow_cli.commands.cli import run  # noqa: E402  (a user error: one line, exit 2)
from evflow_cli.commands.ship import *  # noqa: E402, F401, F403 - `import ship` from scripts/ keeps working
from evflow_cli.commands.ship import main  # noqa: E402

if __name__ == "__main__":
    sys.exit(run(main))
