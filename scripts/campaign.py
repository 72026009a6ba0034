#!/usr/bin/env python
"""Campaigns: long training kept resumable in the repository (evflow_cli/commands/campaign.py)."""
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from evflow_cli.commands.campaign import *  # noqa: E402, F401, F403 - `import campaign` from scripts/ keeps working
from evflow_cli.commands.campaign import main  # noqa: E402
from evflow_cli.commands.cli import run  # noqa: E402

if __name__ == "__main__":
    sys.exit(run(main))
