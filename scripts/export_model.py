#!/usr/bin/env python
"""Ship a trained model: turn a training checkpoint into agents/weights/NAME.pt (weights only) (evflow_cli/commands/export_model.py)."""
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from evflow_cli.commands.cli import run  # noqa: E402  (a user error: one line, exit 2)
from evflow_cli.commands.export_model import *  # noqa: E402, F401, F403 - `import export_model` from scripts/ keeps working
from evflow_cli.commands.export_model import main  # noqa: E402

if __name__ == "__main__":
    sys.exit(run(main))
