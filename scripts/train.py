#!/usr/bin/env python
"""Train a flow policy (evflow_cli/commands/train.py; console command evflow-train)."""
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from evflow_cli.commands.cli import run  # noqa: E402  (a user error: one line, exit 2)
from evflow_cli.commands.train import *  # noqa: E402, F401, F403 - `import train` from scripts/ keeps working
from evflow_cli.commands.train import exit_process, main  # noqa: E402

if __name__ == "__main__":
    exit_process(run(main))  # a torchrun rank ends without the interpreter's finalisation (see there)
