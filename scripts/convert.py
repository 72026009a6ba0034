#!/usr/bin/env python
"""Convert a recording between event formats (evflow_cli/commands/convert.py; console command evflow-convert)."""
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from evflow_cli.commands.cli import run  # noqa: E402  (a user error: one line, exit 2)
from evflow_cli.commands.convert import main  # noqa: E402

if __name__ == "__main__":
    sys.exit(run(main))
