"""Print the trainable parameter count of every model variant as a Markdown table.

Usage: ``python scripts/param_counts.py [--widths paper cpu] [--flops H W]`` (paper = base width
32). ``--flops`` adds a table of the convolution and matrix-product arithmetic of one window
(batch 1, H x W, state carried), in GFLOP, with each model's ratio to ConvGRU-EV-FlowNet's.
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass

from agents import WIDTHS
from agents.options import command_parser, option, options_from_args, positive_int
from evflow_cli.summary import flops_table, parameter_table


@dataclass
class ParamCountsOptions:
    """Which widths scripts/param_counts.py tabulates, and at which input size the arithmetic."""

    widths: list[str] = option(default_factory=lambda: ["paper", "cpu"], choices=sorted(WIDTHS))
    """the named widths (agents.WIDTHS) to count, one column each"""
    flops: tuple[int, int] | None = option(None, nargs=2, type=positive_int, metavar=("H", "W"))
    """also print the GFLOP of one window at this input size"""


def build_parser() -> argparse.ArgumentParser:
    return command_parser(ParamCountsOptions, __doc__)


def main(argv=None) -> int:
    args = options_from_args(ParamCountsOptions, build_parser().parse_args(argv))
    tables = {width: dict(parameter_table(width)) for width in args.widths}
    labels = list(next(iter(tables.values())))
    header = " | ".join(f"{w} (c={WIDTHS[w]})" for w in args.widths)
    print(f"| model | {header} |")
    print("|---|" + "---:|" * len(args.widths))
    for label in labels:
        cells = " | ".join(f"{tables[w][label]:,}" for w in args.widths)
        print(f"| {label} | {cells} |")
    if args.flops:
        height, width = args.flops
        flops = {w: dict(flops_table(w, 1, height, width)) for w in args.widths}
        print(f"\nGFLOP per {height}x{width} window (convolutions and matrix products; x ConvGRU-EV-FlowNet)\n")
        print(f"| model | {header} |")
        print("|---|" + "---:|" * len(args.widths))
        for label in labels:
            cells = " | ".join(
                f"{flops[w][label] / 1e9:.2f} ({flops[w][label] / flops[w]['ConvGRU-EV-FlowNet']:.3f}x)"
                for w in args.widths
            )
            print(f"| {label} | {cells} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
