#!/usr/bin/env python
"""Precompute the teacher's targets of a dataset (per-window contrast maximisation, solved once (evflow_cli/commands/teacher_targets.py)."""
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from evflow_cli.commands.cli import run  # noqa: E402  (a user error: one line, exit 2)
from evflow_cli.commands.teacher_targets import *  # noqa: E402, F401, F403 - `import teacher_targets` from scripts/ keeps working
from evflow_cli.commands.teacher_targets import main  # noqa: E402

if __name__ == "__main__":
    sys.exit(run(main))
