#!/usr/bin/env python
"""Speed benchmarks, one section per part of the project (evflow_cli/commands/benchmark.py; console command evflow-benchmark)."""
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from evflow_cli.commands.benchmark import main  # noqa: E402
from evflow_cli.commands.cli import run  # noqa: E402  (a user error: one line, exit 2)

if __name__ == "__main__":
    sys.exit(run(main))
