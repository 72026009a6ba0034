#!/usr/bin/env python
"""The paper's ablations (Tables 2-4 layout) with the project's recipe, at one budget for all (evflow_cli/commands/ablations.py)."""
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from evflow_cli.commands.ablations import *  # noqa: E402, F401, F403 - `import ablations` from scripts/ keeps working
from evflow_cli.commands.ablations import main  # noqa: E402
from evflow_cli.commands.cli import run  # noqa: E402  (a user error: one line, exit 2)

if __name__ == "__main__":
    sys.exit(run(main))
