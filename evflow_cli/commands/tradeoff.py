"""Accuracy against time per window for the network, the network finished by a short solve, and
the model-free solve at reduced iterations, on the same windows (evflow_cli/tradeoff.py says
what each mode is). Writes OUT/tradeoff.json, OUT/tradeoff.md and OUT/tradeoff.png (with
matplotlib: pip install '.[plots]').

  python scripts/tradeoff.py                                             # devval and synthetic-stress, dt = 1 and 4
  python scripts/tradeoff.py --data ../shared/devval --max-windows 6 --dt 4 --threads 1
  python scripts/tradeoff.py --modes split split+cmax:10 cmax:10 cmax:100 --data synthetic-stress
  python scripts/tradeoff.py --replot runs/a/tradeoff.json runs/b/tradeoff.json --out runs/both   # table and plot again
"""

from __future__ import annotations

import glob
import os
from dataclasses import dataclass
from pathlib import Path

import torch

from agents.options import DeviceOptions, Progress, command_parser, option, options_from_args, positive_int
from envs.outputs import Output
from evflow_cli import tradeoff


@dataclass(kw_only=True)
class TradeoffOptions(DeviceOptions, Progress):
    """Which modes scripts/tradeoff.py measures, on which data, and where it writes."""

    data: list[str] = option(default_factory=lambda: ["../shared/devval", "synthetic-stress"])
    """data sets (a folder of h5 recordings, a file pattern or a synthetic split), one panel each"""
    modes: list[str] = option(default_factory=lambda: list(tradeoff.DEFAULT_MODES))
    """the modes (evflow_cli/tradeoff.py): zero, net, split, split+fine:K, split+cmax:K[@P], cmax:N"""
    model: str | None = None
    """the network: a shipped name or a checkpoint file of scripts/train.py (default: the project's default)"""
    dt: list[int] = option(default_factory=lambda: [1, 4], type=positive_int)
    """window lengths in ground-truth intervals"""
    max_windows: int | None = option(5, type=positive_int)
    """windows per sequence (from its start)"""
    block: str | None = None
    """the learned update block of the +block:K modes (a file of scripts/train_block.py)"""
    reference: str = "cmax:100"
    """the mode the ratios are taken to (one of --modes)"""
    out: str = "runs/tradeoff"
    """output folder"""
    overwrite: bool = False
    """replace the outputs of an earlier run"""
    replot: list[str] = option(default_factory=list, metavar="JSON")
    """measure nothing: table and plot the tradeoff.json files of earlier runs together into --out"""


def _data(item: str) -> tuple[str | list[str], str]:
    """(what evaluate() takes, its label): a folder or pattern becomes its sorted h5 files."""
    if os.path.isdir(item):
        files = sorted(glob.glob(os.path.join(item, "*.h5")))
        if not files:
            raise FileNotFoundError(f"--data {item}: a folder without .h5 recordings")
        return files, Path(item).name
    if any(ch in item for ch in "*?["):
        files = sorted(glob.glob(item))
        if not files:
            raise FileNotFoundError(f"--data {item}: matches no file")
        return files, Path(item).parent.name
    return item, Path(item).stem if item.endswith(".h5") else item


def build_parser():
    return command_parser(TradeoffOptions, __doc__)


def main(argv=None) -> int:
    args = options_from_args(TradeoffOptions, build_parser().parse_args(argv))
    if args.threads:
        torch.set_num_threads(args.threads)
    out = Path(args.out)
    if args.replot:
        points = [p for path in args.replot for p in tradeoff.load_points(path)]
        with Output(out / "tradeoff.md", overwrite=args.overwrite, option="--out") as md_out:
            md = tradeoff.table(points, reference=args.reference)
            md_out.write_text(md + "\n")
        print(md)
        picture = tradeoff.plot(points, out / "tradeoff.png", reference=args.reference)
        print(f"\nwrote {out / 'tradeoff.md'}" + (f", {picture}" if picture else " (no picture: pip install matplotlib)"))
        return 0
    block = None
    if args.block:
        from agents.update_block import load_block

        block, _ = load_block(args.block, device=args.device)
    for mode in args.modes:  # a typo fails here, not after an hour
        tradeoff.build_mode(mode, args.model, 1, args.device, block)
    if args.reference not in args.modes:
        raise ValueError(f"--reference {args.reference}: not one of --modes ({' '.join(args.modes)})")
    sets = [_data(item) for item in args.data]
    points = []
    with Output(out / "tradeoff.json", overwrite=args.overwrite, option="--out") as json_out, \
            Output(out / "tradeoff.md", overwrite=args.overwrite, option="--out") as md_out:
        for data, label in sets:
            points += tradeoff.measure(data, label, args.modes, args.dt, model=args.model, max_windows=args.max_windows,
                                       device=args.device, progress=not args.no_progress, block=block)
            tradeoff.write_json(points, out / "tradeoff.partial.json")  # survives an interruption
        md = tradeoff.table(points, reference=args.reference)
        md_out.write_text(md + "\n")
        json_out.write_text(tradeoff.points_json(points))
    (out / "tradeoff.partial.json").unlink(missing_ok=True)
    print(md)
    picture = tradeoff.plot(points, out / "tradeoff.png", reference=args.reference)
    print(f"\nwrote {out / 'tradeoff.json'}, {out / 'tradeoff.md'}"
          + (f", {picture}" if picture else " (no picture: pip install matplotlib)"))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
