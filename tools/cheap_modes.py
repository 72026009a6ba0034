#!/usr/bin/env python
"""Cheap ways to run a shipped network, side by side in one process: AEE, its ratio to the
``--cmax`` row, in how many sequences the L_HMC is below zero flow's, and the time per window
(and how many times less than the ``--cmax`` row's, measured in the same process).

    python tools/cheap_modes.py --pretrained ev-mgrflownet-cpu-dr --data synthetic-stress --dt 4 \\
        --modes net split coarse:2 pick:net+coarse:2 cmax

Modes (one row each):

- ``net``: the network, one step per window.
- ``mirror:4`` / ``mirror:2`` / ``mirror:lr``: averaged over mirrored copies of its input
  (agents/wrappers/mirror.py): all four mirrors, the input and its half turn, the input and its
  left-right mirror.
- ``split``: stepped through one sub-window per frame of the window (agents/wrappers/subwindows.py).
- ``coarse:F``: the window's events binned on an F-times coarser sensor grid (each F x F block
  of pixels one pixel, the input divided by F^2 so that a block holds what one pixel did), the
  flow upsampled bilinearly and multiplied by F: F^2 times fewer pixels, and F times the output
  range in sensor pixels (agents/wrappers/coarse.py). ``coarse:F:split``: the same stepped
  through the window's frames.
- ``gain:G``: the network's flow times G (a calibration of its magnitude; agents/wrappers/gain.py).
- ``avg:A+B`` / ``pick:A+B``: the mean of the modes' flows / the one whose L_HMC on the window
  (the env's loss, border rule) is lowest; a mode may be ``zero`` here (agents/wrappers/combine.py).
- ``cmax``: per-window contrast maximisation (agents/cmax.py), the reference.

``--truth`` adds the ground truth's own row (AEE 0): in how many sequences its L_HMC, computed
as the evaluation computes a method's, is below zero flow's. A goal of "below zero flow's on
every sequence" that the truth misses asks for invented motion.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402
import torch  # noqa: E402

from agents.cmax import ContrastMaximisationPolicy  # noqa: E402
from agents.evaluation import env_loss, evaluate  # noqa: E402
from agents.policy import RecurrentPolicy, ZeroFlowPolicy  # noqa: E402
from agents.rollout import rollout  # noqa: E402
from agents.wrappers import (  # noqa: E402
    MIRRORS,
    ROTATION,
    CoarsePolicy,
    CombinedPolicy,
    GainPolicy,
    MirrorPolicy,
    SubWindowPolicy,
)
from envs.dataset import resolve_data  # noqa: E402
from envs.env import EventFlowEnv  # noqa: E402


def build(mode: str, name: str, dt: int):
    """The policy of one mode (None: zero flow)."""
    kind, _, rest = mode.partition(":")
    if kind in ("avg", "pick"):
        return CombinedPolicy([build(part, name, dt) for part in rest.split("+")], kind)
    if kind == "zero":
        return None
    if kind == "cmax":
        return ContrastMaximisationPolicy()
    net = RecurrentPolicy.from_pretrained(name)
    if kind == "net":
        return net
    if kind == "mirror":
        return MirrorPolicy(net, {"4": MIRRORS, "2": ROTATION, "lr": ((False, False), (True, False))}[rest])
    if kind == "split":
        return SubWindowPolicy(net, dt)
    if kind == "coarse":
        factor, _, split = rest.partition(":")
        return CoarsePolicy(net, int(factor), dt if split == "split" else 1)
    if kind == "gain":
        return GainPolicy(net, float(rest))
    raise SystemExit(f"unknown mode {mode!r} (see --help)")


def truth_below_zero(data, dt: int, max_windows: int) -> tuple[int, int]:
    """(sequences whose mean L_HMC of the ground truth is below zero flow's, sequences scored),
    over the first ``max_windows`` windows of each; pixels without valid truth get zero flow."""
    below = scored = 0
    for index in range(len(resolve_data(data))):
        env = EventFlowEnv(data, window="frames", window_size=dt, compute_reward=False, sequences=[index])
        sums = np.zeros(2)
        for step in rollout(ZeroFlowPolicy(), env, options={"sequence": 0}, max_windows=max_windows):
            win = step.window
            if len(win.events):
                truth = np.where(win.flow_gt_valid, win.flow_gt, 0).astype(np.float32)
                losses = env_loss(env, truth, win)  # as the evaluation's L_HMC column
                sums += [losses["hmc"], losses["hmc_zero"]]
        env.close()
        below += int(sums[0] < sums[1])
        scored += int(sums[1] > 0)
    return below, scored


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--pretrained", default="ev-mgrflownet-cpu-dr", help="shipped model name")
    p.add_argument("--data", default="synthetic-stress")
    p.add_argument("--dt", type=int, default=1, help="window length in ground-truth intervals")
    p.add_argument("--max-windows", type=int, default=5, help="per sequence")
    p.add_argument("--modes", nargs="+", default=["net", "mirror:2", "coarse:2", "cmax"])
    p.add_argument("--truth", action="store_true", help="add the ground truth's row (see above)")
    p.add_argument("--threads", type=int, default=2)
    args = p.parse_args(argv)
    torch.set_num_threads(args.threads)
    rows = []
    for mode in args.modes:
        policy = build(mode, args.pretrained, args.dt)
        start = time.time()
        results = evaluate(policy, args.data, window_size=args.dt, max_windows=args.max_windows, progress=False)
        aee = float(np.mean([r.mean("aee") for r in results]))
        below = sum(r.mean("hmc") < r.mean("hmc_zero") for r in results if r.counts["hmc"])
        ms = sum(r.sums["ms"] for r in results) / max(1, sum(r.counts["ms"] for r in results))
        picked = f" picked {policy.picked}" if isinstance(policy, CombinedPolicy) and policy.how == "pick" else ""
        rows.append((mode, aee, below, len(results), ms))
        per_sequence = ", ".join(f"{r.name.removeprefix(args.data + '-')} {r.mean('aee'):.2f}" for r in results)
        print(f"[{mode}] AEE {aee:.3f}, {time.time() - start:.0f} s{picked}; per sequence: {per_sequence}",
              file=sys.stderr, flush=True)
    ref = {mode: (aee, ms) for mode, aee, _, _, ms in rows}.get("cmax")
    print(f"**{args.pretrained}, {args.data}, dt = {args.dt}, first {args.max_windows} windows per sequence**\n")
    print("| mode | mean AEE | x `--cmax` | seq. L_HMC < zero | ms/win | x less time than `--cmax` |")
    print("|---|---:|---:|---:|---:|---:|")
    for mode, aee, below, n, ms in rows:
        ratio = f"{aee / ref[0]:.2f}" if ref else "-"
        faster = f"{ref[1] / ms:.1f}" if ref and ms > 0 else "-"
        print(f"| {mode} | {aee:.3f} | {ratio} | {below}/{n} | {ms:.0f} | {faster} |")
    if args.truth:
        below, scored = truth_below_zero(args.data, args.dt, args.max_windows)
        print(f"| ground truth | 0 | 0 | {below}/{scored} | - | - |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
