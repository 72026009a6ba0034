"""Print the trainable parameter count of every model variant as a Markdown table.

Usage: ``python scripts/param_counts.py [--widths paper cpu] [--flops H W]`` (paper = base width
32). ``--flops`` adds a table of the convolution and matrix-product arithmetic of one window
(batch 1, H x W, state carried), in GFLOP, with each model's ratio to ConvGRU-EV-FlowNet's.
"""

from __future__ import annotations

import argparse

from agents import WIDTHS
from agents.summary import flops_table, parameter_table


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--widths", nargs="+", default=["paper", "cpu"], choices=sorted(WIDTHS))
    parser.add_argument("--flops", nargs=2, type=int, metavar=("H", "W"), default=None,
                        help="also print the GFLOP of one window at this input size")
    args = parser.parse_args(argv)
    if args.flops and min(args.flops) < 1:
        parser.error(f"--flops: H and W must be positive, got {args.flops[0]} {args.flops[1]}")
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
