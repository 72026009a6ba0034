#!/usr/bin/env python
"""Campaigns: long training kept resumable in the repository (agents/commands/campaign.py)."""
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from agents.commands.campaign import *  # noqa: E402, F401, F403 - `import campaign` from scripts/ keeps working
from agents.commands.campaign import main  # noqa: E402
from agents.commands.cli import run  # noqa: E402

if __name__ == "__main__":
    sys.exit(run(main))
