#!/usr/bin/env python
"""How much of a split's error no network with a bounded output can remove: the AEE of the
ground truth itself clipped to +-flow_scaling pixels per component (a tanh head times
flow_scaling cannot say more), beside zero flow's, per sequence, on the first windows of each.

    python tools/range_floor.py --data synthetic-stress --max-windows 5 --flow-scaling 32
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402

from envs.dataset import resolve_data  # noqa: E402
from envs.env import EventFlowEnv  # noqa: E402
from envs.representations import event_mask  # noqa: E402
from losses import flow_error  # noqa: E402


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", default="synthetic-stress")
    p.add_argument("--max-windows", type=int, default=5, help="per sequence")
    p.add_argument("--dt", type=int, nargs="+", default=[1, 4])
    p.add_argument("--flow-scaling", type=float, nargs="+", default=[32.0])
    args = p.parse_args(argv)
    names = [source.name for source in resolve_data(args.data)]
    print("| sequence | dt | zero flow AEE | " + " | ".join(f"floor at +-{s:g} px" for s in args.flow_scaling) + " |")
    print("|---|---:|---:|" + "---:|" * len(args.flow_scaling))
    totals: dict = {}
    for dt in args.dt:
        for index, name in enumerate(names):
            env = EventFlowEnv(args.data, window="frames", window_size=dt, compute_reward=False, sequences=[index])
            _, info = env.reset(options={"sequence": 0})
            sums, n = np.zeros(1 + len(args.flow_scaling)), 0
            for _ in range(args.max_windows):
                gt, valid = info["flow_gt"], info["flow_gt_valid"]
                mask = event_mask(info["window"].events, env.sensor_size)
                zero = flow_error(np.zeros_like(gt), gt, valid, mask)
                if zero["n_pixels"]:
                    floors = [flow_error(np.clip(gt, -s, s), gt, valid, mask)["aee"] for s in args.flow_scaling]
                    sums += [zero["aee"], *floors]
                    n += 1
                _, _, _, truncated, info = env.step(np.zeros((2, *env.sensor_size), np.float32))
                if truncated:
                    break
            env.close()
            if n:
                means = sums / n
                totals.setdefault(dt, []).append(means)
                print(f"| {name} | {dt} | " + " | ".join(f"{v:.3f}" for v in means) + " |", flush=True)
    for dt, rows in totals.items():
        print(f"| mean over sequences | {dt} | " + " | ".join(f"{v:.3f}" for v in np.mean(rows, 0)) + " |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
