#!/usr/bin/env python
"""Compare settings of per-window contrast maximisation (agents/cmax.py) on a split: AEE,
L_HMC and time per window, at dt = 1 and dt = 4, on the first windows of every sequence.

    python tools/compare_cmax.py --data synthetic-test --max-windows 4

Settings compared: "coarse-sensor" (the default of ``--cmax``: flow grids 4-8-16 on a sensor
grid 4x, 2x, then 1x coarser, 40/30/30 Adam steps, step size decayed 10x) against "plain" (the
teacher targets' solve: grids 4-8-16 on sensor pixels, 40 steps each, constant step size).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from agents.cmax import PLAIN, CMaxSettings, ContrastMaximisationPolicy  # noqa: E402
from agents.evaluation import evaluate, results_table  # noqa: E402

SETTINGS = {"coarse-sensor": CMaxSettings(), "plain": PLAIN}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", nargs="+", default=["synthetic-test"])
    p.add_argument("--max-windows", type=int, default=4, help="per sequence")
    p.add_argument("--dt", type=int, nargs="+", default=[1, 4])
    p.add_argument("--settings", nargs="+", default=list(SETTINGS), choices=list(SETTINGS))
    p.add_argument("--lr", type=float, nargs="*", default=None, help="override lr_per_frame (one row per value)")
    args = p.parse_args(argv)
    data = args.data[0] if len(args.data) == 1 else args.data
    rows = {}
    for name in args.settings:
        for lr in args.lr or [None]:
            settings = SETTINGS[name] if lr is None else CMaxSettings(**{**SETTINGS[name].describe(), "lr_per_frame": lr})
            rows[name if lr is None else f"{name} lr {lr}"] = ContrastMaximisationPolicy(settings)
    rows["zero flow"] = None
    print_comparison(rows, data, args.dt, args.max_windows)
    return 0


def print_comparison(rows: dict, data, dts, max_windows: int) -> None:
    """One table per window length of the named policies (None: zero flow) on ``data``."""
    for dt in dts:
        named = {k: evaluate(v, data, window_size=dt, max_windows=max_windows, progress=False)
                 for k, v in rows.items()}
        print(results_table(named, title=f"dt = {dt}, first {max_windows} windows per sequence",
                            per_sequence=False) + "\n", flush=True)


if __name__ == "__main__":
    sys.exit(main())
