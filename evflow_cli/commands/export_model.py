"""Ship a trained model: turn a training checkpoint into agents/weights/NAME.pt (weights only)
and NAME.json (provenance), loadable with RecurrentPolicy.from_pretrained(NAME) and
scripts/evaluate.py --pretrained NAME.

  python scripts/export_model.py runs/ship/train/checkpoint.pt --name ev-mgrflownet-cpu-synthetic \\
      --command "python scripts/train.py ..." --eval runs/ship/eval/results.json

The provenance records the command, the training data and budget (from the checkpoint's config
and the run's metrics.jsonl, by default the one beside it, counted up to the checkpoint's step),
the date, and the evaluation metrics when --eval is given.

  python scripts/export_model.py --upgrade runs/old/checkpoint.pt [MORE.pt ...]

converts, in place, checkpoints written before the safe format (pickled numpy objects, refused by
the safe loader) so that they load with weights_only=True. This unpickles them once: only for
files you trust.
"""

from __future__ import annotations

import argparse
import datetime
import json
from dataclasses import dataclass
from pathlib import Path

from agents.checkpoint import load_checkpoint, upgrade_checkpoint
from agents.options import command_parser, option, options_from_args
from agents.pretrained import check_model_file_name, export_pretrained


@dataclass(kw_only=True)
class ExportOptions:
    """What scripts/export_model.py ships (or upgrades) and the provenance it records."""

    checkpoint: list[str] = option(positional=True, nargs="+")
    """the training checkpoint (several with --upgrade)"""
    name: str | None = None
    """the shipped model's name (required unless --upgrade)"""
    upgrade: bool = False
    """convert old-format checkpoints in place to the safe format, then stop (trusted files only)"""
    command: str = ""
    """the command(s) that trained it"""
    eval: str | None = None
    """results.json of scripts/evaluate.py on the model"""
    note: str = ""
    """what the model is, for the provenance"""
    dir: str | None = None
    """where the weights go (default: agents/weights/)"""
    metrics: str | None = None
    """the run's metrics.jsonl (default: beside the checkpoint)"""
    overwrite: bool = False
    """replace a model of that name already in the weights folder"""


def build_parser() -> argparse.ArgumentParser:
    return command_parser(ExportOptions, __doc__)


def main(argv=None) -> int:
    p = build_parser()
    args = options_from_args(ExportOptions, p.parse_args(argv))
    if args.upgrade:
        for path in args.checkpoint:
            print(f"upgraded {upgrade_checkpoint(path)}")
        return 0
    if args.name is None or len(args.checkpoint) != 1:
        p.error("exporting takes one checkpoint and --name NAME")
    try:
        check_model_file_name(args.name, "--name")
    except ValueError as err:
        p.error(str(err))
    ckpt = Path(args.checkpoint[0])
    step = int(load_checkpoint(ckpt)["step"])
    metrics = Path(args.metrics) if args.metrics else ckpt.parent / "metrics.jsonl"
    budget = {}
    if metrics.exists():
        rows = [json.loads(line) for line in metrics.read_text().splitlines() if line.strip()]
        logged = [r for r in rows if "loss" in r and r["step"] <= step]
        seconds, last = 0.0, 0.0
        for r in logged:  # elapsed_s restarts at each --resume: add up the segments
            e = r.get("elapsed_s", 0.0)
            if e < last:
                seconds += last
            last = e
        seconds += last
        # one row per step up to the checkpoint's (a resume re-logs the steps after the last save)
        steps = {r["step"]: r for r in logged}
        budget = {"optimizer_steps": step,
                  "training_windows": int(sum(r.get("windows", 0) for r in steps.values())),
                  "wall_minutes": round(seconds / 60, 1)}
    provenance = {"command": args.command, "date": datetime.date.today().isoformat(), "budget": budget, "note": args.note}
    if args.eval:
        provenance["evaluation"] = json.loads(Path(args.eval).read_text())
    weights, meta = export_pretrained(ckpt, args.name, provenance, args.dir, overwrite=args.overwrite)
    print(f"wrote {weights} ({weights.stat().st_size / 1e6:.1f} MB) and {meta}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
