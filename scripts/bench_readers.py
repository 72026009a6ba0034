#!/usr/bin/env python
"""Reader speed and memory per format (evflow_cli/commands/bench_readers.py)."""
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from evflow_cli.commands.bench_readers import main  # noqa: E402

if __name__ == "__main__":
    sys.exit(main())
