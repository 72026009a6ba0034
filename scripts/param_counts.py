#!/usr/bin/env python
"""Print the trainable parameter count of every model variant as a Markdown table (evflow_cli/commands/param_counts.py)."""
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from evflow_cli.commands.cli import run  # noqa: E402  (a user error: one line, exit 2)
from evflow_cli.commands.param_counts import *  # noqa: E402, F401, F403 - `import param_counts` from scripts/ keeps working
from evflow_cli.commands.param_counts import main  # noqa: E402

if __name__ == "__main__":
    sys.exit(run(main))
