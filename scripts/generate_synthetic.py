#!/usr/bin/env python
"""Generate the synthetic splits to files or the disk cache (evflow_cli/commands/generate.py; console command evflow-generate)."""
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from evflow_cli.commands.cli import run  # noqa: E402  (a user error: one line, exit 2)
from evflow_cli.commands.generate import main  # noqa: E402

if __name__ == "__main__":
    sys.exit(run(main))
