#!/usr/bin/env python
"""The main job, end to end on the embedded synthetic benchmark (no files needed) (evflow_cli/commands/main_job.py)."""
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from evflow_cli.commands.cli import run  # noqa: E402  (a user error: one line, exit 2)
from evflow_cli.commands.main_job import *  # noqa: E402, F401, F403 - `import main` from scripts/ keeps working
from evflow_cli.commands.main_job import main  # noqa: E402

if __name__ == "__main__":
    sys.exit(run(main))
