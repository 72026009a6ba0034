"""Precompute the teacher's targets of a dataset (per-window contrast maximisation, solved once
on full frames) for ``scripts/train.py --loss teacher --teacher-cache FILE``.

    python scripts/teacher_targets.py --data synthetic-train --out runs/teacher-targets/train.h5
    python scripts/teacher_targets.py --data synthetic-dr-train:32 --out runs/teacher-targets/dr32.h5 \\
        --sensor-scales 4 2 1 --steps 40 30 30 --lr-per-frame 0.3 --lr-decay 10     # coarse sensor grid
    python scripts/teacher_targets.py --merge old.h5:1 strong.h5:2,4 --out merged.h5    # windows from several files
    python scripts/teacher_targets.py --derive-from runs/teacher-targets/dr32.h5 --from-size 2 --smooth 1 \\
        --out runs/teacher-targets/dr32-from2-smooth1.h5      # 1-4 frame targets from the 2-frame ones
    python scripts/train.py --loss teacher --teacher-cache runs/teacher-targets/train.h5 --window-size 1 2 3 4 ...

Every window of every recording at each ``--window-size`` (frames) is solved; the file is
written recording by recording into OUT.parts/ (an interrupted run resumes there) and assembled into
OUT when complete. On the project's 2-core CPU synthetic-train (32 recordings, sizes 1-4,
~3,900 windows) takes about 15-25 minutes. See agents/teacher.py for the file layout.
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from tqdm import tqdm

from agents.options import (
    DeviceOptions,
    Progress,
    WindowSize,
    command_parser,
    non_negative_float,
    non_negative_int,
    option,
    options_from_args,
    positive_float,
    positive_int,
)
from agents.teacher import TeacherSettings, TeacherTargets, compute_teacher_targets, count_windows

#: the window lengths (frames) solved when --window-size is not given
DEFAULT_WINDOW_SIZES = [1, 2, 3, 4]


@dataclass(kw_only=True)
class TeacherTargetsOptions(WindowSize, DeviceOptions, Progress):
    """What scripts/teacher_targets.py solves (or scores, merges, derives) and where it writes;
    the solver's defaults are TeacherSettings' (its loss weights CMAX_WEIGHTS')."""

    data: list[str] = option(default_factory=lambda: ["synthetic-train"])
    """synthetic split name, recording files or folders"""
    out: Path = option(required=True)
    """output h5 file (with --score: the file to score)"""
    score: bool = False
    """do not solve: score the targets in --out against the ground truth (AEE vs zero flow's)"""
    derive_from: Path | None = option(None, metavar="TARGETS")
    """do not solve: derive --out's windows from the --from-size-frame windows of this target file (their velocity, optionally smoothed, times each window's duration)"""
    from_size: int = option(2, type=positive_int)
    """with --derive-from: the window length solved (frames)"""
    smooth: int = option(0, type=non_negative_int)
    """with --derive-from: average each long window's velocity with this many neighbours a side"""
    merge: list[str] | None = option(None, metavar="FILE:SIZES")
    """do not solve: --out takes the windows of each FILE whose length is one of SIZES frames (comma-separated), e.g. old.h5:1 strong.h5:2,4 (float16 grids, compressed)"""
    grids: tuple[int, ...] = option(TeacherSettings.grids, type=positive_int)
    """coarse-to-fine grid cells along the longer side"""
    steps: tuple[int, ...] = option((TeacherSettings.steps,), type=positive_int)
    """Adam steps per level: one for all levels, or one per level"""
    sensor_scales: tuple[int, ...] | None = option(None, type=positive_int)
    """sensor-grid coarsening per level, e.g. 4 2 1 (default: sensor pixels throughout)"""
    lr_decay: float = option(TeacherSettings.lr_decay, type=positive_float)
    """step size falls by this factor over a solve"""
    lr_per_frame: float = option(TeacherSettings.lr_per_frame, type=positive_float)
    """Adam step size in pixels per frame of window length"""
    lambda_2: float = option(TeacherSettings.lambda_2, type=non_negative_float)
    """smoothness weight"""
    flow_scaling: float = option(TeacherSettings.flow_scaling, type=positive_float)
    """the loss's flow scaling"""
    evidence_prior: float = option(0.0, metavar="C", type=non_negative_float)
    """hold each window's solve toward zero flow with weight C / its events (agents/cmax.py; 30000 as measured): still, sparse windows stay still"""
    max_windows: int | None = option(None, type=positive_int)
    """only the first N windows of each recording and size (solving or --score; not for training)"""
    batch_size: int = option(16, type=positive_int)
    """windows solved together"""


def build_parser() -> argparse.ArgumentParser:
    return command_parser(TeacherTargetsOptions, __doc__)


#: the options of a solve: without one (--score, --merge, --derive-from) giving them is a mistake
SOLVER_OPTIONS = ("grids", "steps", "sensor_scales", "lr_decay", "lr_per_frame", "lambda_2", "flow_scaling",
                  "evidence_prior", "batch_size")


def _misplaced_solver_options(args: TeacherTargetsOptions) -> list[str]:
    """The solver options set away from their defaults when the command solves nothing."""
    defaults = TeacherTargetsOptions(out=args.out)
    return [f"--{name.replace('_', '-')}" for name in SOLVER_OPTIONS if getattr(args, name) != getattr(defaults, name)]


def main(argv=None) -> int:
    parser = build_parser()
    args = options_from_args(TeacherTargetsOptions, parser.parse_args(argv))
    args.set_threads()
    mode = "--score" if args.score else "--merge" if args.merge else "--derive-from" if args.derive_from else None
    misplaced = _misplaced_solver_options(args) if mode else []
    if misplaced:
        parser.error(f"{', '.join(misplaced)} set the solve, which {mode} does not run "
                     "(derived and merged targets keep their sources' settings)")
    if args.score:
        from agents.teacher import score_targets

        for k, row in score_targets(args.out, max_windows=args.max_windows, window_sizes=args.window_sizes()).items():
            print(f"{k}-frame windows: targets' AEE {row['aee']:.3f}, zero flow's {row['aee_zero']:.3f} "
                  f"({row['ratio']:.2f}x) over {row['windows']} windows")
        return 0
    sizes = args.window_sizes() or DEFAULT_WINDOW_SIZES
    if args.out.exists():
        print(f"{args.out} exists; delete it to recompute", file=sys.stderr)
        return 1
    if args.merge:
        from agents.teacher import merge_targets

        parts = []
        for item in args.merge:
            path, sep, lengths = item.rpartition(":")
            if not sep or not all(k.strip().isdigit() for k in lengths.split(",")):
                raise SystemExit(f"--merge {item!r}: expected FILE:SIZES, e.g. strong.h5:2,4")
            parts.append((Path(path), [int(k) for k in lengths.split(",")]))
        merge_targets(parts, args.out, dtype=np.float16)
        print(f"{args.out}: {len(TeacherTargets(args.out))} windows merged from {', '.join(args.merge)}")
        return 0
    if args.derive_from is not None:
        from agents.teacher import derive_targets

        derive_targets(args.derive_from, args.out, from_size=args.from_size, smooth=args.smooth,
                       window_sizes=sizes)
        print(f"{args.out}: derived from the {args.from_size}-frame windows of {args.derive_from}")
        return 0
    data = args.data[0] if len(args.data) == 1 else args.data
    steps = args.steps[0] if len(args.steps) == 1 else tuple(args.steps)
    settings = TeacherSettings(grids=tuple(args.grids), steps=steps, lr_per_frame=args.lr_per_frame,
                               lambda_2=args.lambda_2, flow_scaling=args.flow_scaling, lr_decay=args.lr_decay,
                               evidence_prior=args.evidence_prior,
                               sensor_scales=None if args.sensor_scales is None else tuple(args.sensor_scales))
    total = count_windows(data, sizes, args.max_windows)
    bar = tqdm(total=total, unit="win", disable=args.no_progress)
    start = time.perf_counter()

    def progress(n: int, name: str) -> None:
        bar.set_postfix_str(name)
        bar.update(n)

    compute_teacher_targets(data, args.out, window_sizes=sizes, settings=settings,
                            batch_size=args.batch_size, device=args.device, progress=progress,
                            max_windows=args.max_windows)
    bar.close()
    print(f"{args.out}: {total} windows in {time.perf_counter() - start:.0f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
