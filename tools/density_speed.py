#!/usr/bin/env python
"""How many events a window holds at a given speed: events per pixel per frame interval, binned by
the window's mean speed (px per frame), per dataset, with the share of the pixels that fire and the
events per firing pixel (few edges, or weak ones?). A network that learned on data where fast
motion always comes with dense events can read the speed off the density; this table shows
whether a validation set keeps that relation.

    python tools/density_speed.py --data synthetic-test --data ../shared/devval/*.h5
    python tools/density_speed.py --targets agents/campaigns/mgr-derived/targets.h5   # a training split

The speed is the mean |flow| over the window's valid ground-truth pixels (``--data``), or over every
cell of a teacher-target file's coarse grid (``--targets``: the split it was made on, which has no
ground truth; comparable with the first where the ground truth covers the frame, as on the
synthetic splits and devval); windows of ``--dt`` frames (of the file's windows, those of that
many frame intervals).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import h5py  # noqa: E402
import numpy as np  # noqa: E402

from agents.teacher import TeacherTargets  # noqa: E402
from envs.dataset import resolve_data  # noqa: E402
from envs.representations import event_mask  # noqa: E402
from envs.windows import window_bounds, window_grid  # noqa: E402

SPEED_BINS = (0.0, 0.5, 1.0, 2.0, 4.0, 8.0, 16.0, np.inf)


def firing_share(reader, i0: int, i1: int, height: int, width: int) -> float:
    """The share of the frame's pixels with at least one of the events ``[i0, i1)``."""
    if i1 <= i0:
        return 0.0
    return float(event_mask(reader.events_range(int(i0), int(i1)), (height, width)).mean())


def from_ground_truth(data, dt: int) -> np.ndarray:
    """(N, 3): per window of ``dt`` frames with ground truth, its mean speed (px per frame), its
    events per pixel per frame and the share of pixels that fire in it."""
    rows = []
    for source in resolve_data(data):
        with source.reader() as reader:
            height, width = reader.sensor_size
            for t0, t1, i0, i1 in window_bounds(reader, "frames", dt):
                gt = reader.flow_between(int(t0), int(t1))
                if gt is None:
                    continue
                flow, valid = gt
                if valid.any():
                    speed = float(np.linalg.norm(flow, axis=0)[valid].mean()) / dt
                    rows.append((speed, (int(i1) - int(i0)) / (height * width * dt),
                                 firing_share(reader, i0, i1, height, width)))
    return np.array(rows, float).reshape(-1, 3)


def from_targets(path: str, dt: int) -> np.ndarray:
    """The same from a teacher-target file: the targets' coarse grids as the flow, the windows
    counted in frame intervals of the recording they were made on (the median step of its
    ``frames`` grid)."""
    targets = TeacherTargets(path)
    sources = {s.name: s for s in resolve_data(targets.config["data"])}
    rows = []
    with h5py.File(path, "r") as f:
        for name, group in f.items():
            if name not in sources:
                raise ValueError(f"{path}: recording {name!r} is not in the targets' data {targets.config['data']!r}")
            with sources[name].reader() as reader:
                frame = float(np.median(np.diff(window_grid(reader)[0])))
                height, width = targets.sensor_size_of(name)
                for (t0, t1), grid in zip(group["bounds"][()], group["grid"][()]):
                    if round((t1 - t0) / frame) != dt:
                        continue
                    i0, i1 = reader.index_at(int(t0)), reader.index_at(int(t1))
                    rows.append((float(np.linalg.norm(grid, axis=0).mean()) / dt, (i1 - i0) / (height * width * dt),
                                 firing_share(reader, i0, i1, height, width)))
    return np.array(rows, float).reshape(-1, 3)


def table(name: str, rows: np.ndarray, dt: int = 1) -> list[str]:
    lines = [f"**{name}**: {len(rows)} windows", "",
             "| mean speed (px/frame) | windows | events/px/frame: median | 10th pct | 90th pct "
             "| pixels that fire: median | events per firing pixel: median |",
             "|---|---:|---:|---:|---:|---:|---:|"]
    for low, high in zip(SPEED_BINS, SPEED_BINS[1:]):
        inside = (rows[:, 0] >= low) & (rows[:, 0] < high)
        if inside.any():
            d, share = rows[inside, 1], rows[inside, 2]
            per_firing = rows[inside, 1] * dt / np.maximum(share, 1e-12)
            lines.append(f"| [{low:g},{high:g}) | {int(inside.sum())} | {np.median(d):.3f} | "
                         f"{np.percentile(d, 10):.3f} | {np.percentile(d, 90):.3f} | {100 * np.median(share):.0f} % | "
                         f"{np.median(per_firing):.2f} |")
    return lines + [""]


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", nargs="+", action="append", default=[],
                   help="a dataset with ground truth (a synthetic split, or recording files); repeatable")
    p.add_argument("--targets", action="append", default=[], help="a teacher-target file (its split); repeatable")
    p.add_argument("--dt", type=int, default=1, help="window length in frame intervals (default 1)")
    args = p.parse_args(argv)
    if not args.data and not args.targets:
        p.error("give --data and/or --targets")
    for data in args.data:
        value = data[0] if len(data) == 1 else data
        name = value if isinstance(value, str) else f"{Path(data[0]).parent.name} ({len(data)} files)"
        print("\n".join(table(f"{name}, dt = {args.dt}", from_ground_truth(value, args.dt), args.dt)))
    for path in args.targets:
        print("\n".join(table(f"teacher targets {path}, dt = {args.dt}", from_targets(path, args.dt), args.dt)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
