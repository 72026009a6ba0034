"""Print the trainable parameter count of every model variant as a Markdown table.

Usage: ``python scripts/param_counts.py [--widths paper cpu]`` (paper = base width 32).
"""

from __future__ import annotations

import argparse
import os
import sys

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from agents import WIDTHS  # noqa: E402
from agents.summary import parameter_table  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--widths", nargs="+", default=["paper", "cpu"], choices=sorted(WIDTHS))
    args = parser.parse_args()
    tables = {width: dict(parameter_table(width)) for width in args.widths}
    labels = list(next(iter(tables.values())))
    header = " | ".join(f"{w} (c={WIDTHS[w]})" for w in args.widths)
    print(f"| model | {header} |")
    print("|---|" + "---:|" * len(args.widths))
    for label in labels:
        cells = " | ".join(f"{tables[w][label]:,}" for w in args.widths)
        print(f"| {label} | {cells} |")


if __name__ == "__main__":
    main()
