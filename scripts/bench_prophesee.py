#!/usr/bin/env python
"""Prophesee RAW reading and predict timings (evflow_cli/commands/bench_prophesee.py)."""
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from evflow_cli.commands.bench_prophesee import main  # noqa: E402

if __name__ == "__main__":
    sys.exit(main())
