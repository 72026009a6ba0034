"""Precompute the teacher's targets of a dataset (per-window contrast maximisation, solved once
on full frames) for ``scripts/train.py --loss teacher --teacher-cache FILE``.

    python scripts/teacher_targets.py --data synthetic-train --out runs/teacher-targets/train.h5
    python scripts/teacher_targets.py --data synthetic-dr-train:32 --out runs/teacher-targets/dr32.h5 \
        --sensor-scales 4 2 1 --steps 40 30 30 --lr-per-frame 0.3 --lr-decay 10     # coarse sensor grid
    python scripts/teacher_targets.py --merge old.h5:1 strong.h5:2,4 --out merged.h5    # windows from several files
    python scripts/teacher_targets.py --derive-from runs/teacher-targets/dr32.h5 --from-size 2 --smooth 1 \
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
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from agents.teacher import TeacherSettings, TeacherTargets, compute_teacher_targets, count_windows


def build_parser() -> argparse.ArgumentParser:
    d = TeacherSettings()
    p = argparse.ArgumentParser(description="Precompute per-window contrast-maximisation flows (teacher targets) "
                                "of a dataset, for training with --loss teacher --teacher-cache.")
    p.add_argument("--data", nargs="+", default=["synthetic-train"], help="synthetic split name, recording files or folders")
    p.add_argument("--out", required=True, type=Path, help="output h5 file (with --score: the file to score)")
    p.add_argument("--score", action="store_true",
                   help="do not solve: score the targets in --out against the ground truth (AEE vs zero flow's)")
    p.add_argument("--derive-from", type=Path, default=None, metavar="TARGETS",
                   help="do not solve: derive --out's windows from the --from-size-frame windows of this target file "
                        "(their velocity, optionally smoothed, times each window's duration)")
    p.add_argument("--from-size", type=int, default=2, help="with --derive-from: the window length solved (frames)")
    p.add_argument("--smooth", type=int, default=0,
                   help="with --derive-from: average each long window's velocity with this many neighbours a side")
    p.add_argument("--merge", nargs="+", default=None, metavar="FILE:SIZES",
                   help="do not solve: --out takes the windows of each FILE whose length is one of SIZES frames "
                        "(comma-separated), e.g. old.h5:1 strong.h5:2,4 (float16 grids, compressed)")
    p.add_argument("--window-size", type=int, nargs="+", default=None,
                   help="window lengths in frames (default 1 2 3 4; with --score, the file's)")
    p.add_argument("--grids", type=int, nargs="+", default=list(d.grids),
                   help="coarse-to-fine grid cells along the longer side (default 4 8 16)")
    p.add_argument("--steps", type=int, nargs="+", default=[d.steps],
                   help="Adam steps per level: one for all levels, or one per level (default 40)")
    p.add_argument("--sensor-scales", type=int, nargs="+", default=None,
                   help="sensor-grid coarsening per level, e.g. 4 2 1 (default: sensor pixels throughout)")
    p.add_argument("--lr-decay", type=float, default=d.lr_decay, help="step size falls by this factor over a solve")
    p.add_argument("--lr-per-frame", type=float, default=d.lr_per_frame,
                   help="Adam step size in pixels per frame of window length (default 0.05)")
    p.add_argument("--lambda-2", type=float, default=d.lambda_2, help="smoothness weight (default 0.01)")
    p.add_argument("--flow-scaling", type=float, default=d.flow_scaling, help="the loss's flow scaling (default 32)")
    p.add_argument("--max-windows", type=int, default=None,
                   help="only the first N windows of each recording and size (solving or --score; not for training)")
    p.add_argument("--batch-size", type=int, default=16, help="windows solved together")
    p.add_argument("--device", default="cpu")
    p.add_argument("--threads", type=int, default=None, help="torch CPU threads")
    p.add_argument("--no-progress", action="store_true")
    return p


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    if args.score:
        from agents.teacher import score_targets

        for k, row in score_targets(args.out, max_windows=args.max_windows, window_sizes=args.window_size).items():
            print(f"{k}-frame windows: targets' AEE {row['aee']:.3f}, zero flow's {row['aee_zero']:.3f} "
                  f"({row['ratio']:.2f}x) over {row['windows']} windows")
        return 0
    args.window_size = args.window_size or [1, 2, 3, 4]
    if args.out.exists():
        print(f"{args.out} exists; delete it to recompute", file=sys.stderr)
        return 1
    if args.merge:
        from agents.teacher import merge_targets

        parts = []
        for item in args.merge:
            path, sep, sizes = item.rpartition(":")
            if not sep or not all(k.strip().isdigit() for k in sizes.split(",")):
                raise SystemExit(f"--merge {item!r}: expected FILE:SIZES, e.g. strong.h5:2,4")
            parts.append((Path(path), [int(k) for k in sizes.split(",")]))
        merge_targets(parts, args.out, dtype=np.float16)
        print(f"{args.out}: {len(TeacherTargets(args.out))} windows merged from {', '.join(args.merge)}")
        return 0
    if args.derive_from is not None:
        from agents.teacher import derive_targets

        derive_targets(args.derive_from, args.out, from_size=args.from_size, smooth=args.smooth,
                       window_sizes=args.window_size)
        print(f"{args.out}: derived from the {args.from_size}-frame windows of {args.derive_from}")
        return 0
    data = args.data[0] if len(args.data) == 1 else args.data
    steps = args.steps[0] if len(args.steps) == 1 else tuple(args.steps)
    settings = TeacherSettings(grids=tuple(args.grids), steps=steps, lr_per_frame=args.lr_per_frame,
                               lambda_2=args.lambda_2, flow_scaling=args.flow_scaling, lr_decay=args.lr_decay,
                               sensor_scales=None if args.sensor_scales is None else tuple(args.sensor_scales))
    total = count_windows(data, args.window_size, args.max_windows)
    bar = tqdm(total=total, unit="win", disable=args.no_progress)
    start = time.perf_counter()

    def progress(n: int, name: str) -> None:
        bar.set_postfix_str(name)
        bar.update(n)

    compute_teacher_targets(data, args.out, window_sizes=args.window_size, settings=settings,
                            batch_size=args.batch_size, device=args.device, progress=progress,
                            max_windows=args.max_windows)
    bar.close()
    print(f"{args.out}: {total} windows in {time.perf_counter() - start:.0f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
