#!/usr/bin/env python
"""Loss-landscape diagnostics on synthetic windows (no network), used in the rounds of docs/history/.

  python tools/diagnose.py scale   --window-size 1      # L_HMC of c x ground truth, c = 0 .. 2
  python tools/diagnose.py teacher --window-size 1      # per-window contrast maximisation vs truth
  python tools/diagnose.py overfit --window-size 3      # can a network fit the loss on one fixed batch?
  python tools/diagnose.py border  --window-size 1      # what the border rule costs the true flow
  python tools/diagnose.py targets --cache runs/tt/train.h5   # precomputed teacher targets vs truth

border: for windows of the training split, the true flow's loss divided by zero flow's without
and with the border rule (weight 1 x zero flow's loss x share of splat weight dropped, summed
over the two reference times), plain and with each --ramps distance ramp; how often the truth
beats zero flow, and the share it drops; and, under each rule, the best of a sweep of constant
actions (the game the rule must stop) divided by zero flow's loss.
scale: for windows of the training split, the loss (with the border rule) of c x the true
flow divided by zero flow's, for c in 0.5, 0.75, 1, 1.25, 1.5, 2: the mean ratio per c, the share
of windows where the truth beats zero flow, and how often each c is the best.
teacher: ``losses.contrast_maximisation_flow`` on a batch of windows: AEE against the truth
(pixels with events and valid truth) and the cosine, beside zero flow's AEE.
targets: every window of a precomputed teacher-target file (scripts/teacher_targets.py) against
the truth, per window size: AEE and cosine on pixels with events and valid truth, beside zero
flow's AEE (whole frames, no flips).
overfit: a CPU-width EV-FlowNet (voxel input, near-zero heads) trained with L_HMC on one fixed
batch of windows (the second window of every --sequences-th sequence): loss / zero flow's, AEE
and cosine every 30 steps.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402
import torch  # noqa: E402
import torch.nn.functional as F  # noqa: E402

from envs.env import EventFlowEnv  # noqa: E402
from losses import (  # noqa: E402
    CMAX_WEIGHTS,
    EventBatch,
    LossSpec,
    contrast_maximisation_flow,
    event_pixel_mask,
    window_loss,
    zero_flow_loss,
)

SCALES = (0.5, 0.75, 1.0, 1.25, 1.5, 2.0)
#: The border rule as the rounds that used these diagnostics measured it: weight 1, no ramp.
PLAIN_RULE = LossSpec(border_ramp=0.0)
#: L_HMC without the border rule (the paper's loss).
NO_RULE = LossSpec(border_penalty=0.0)


def windows(args) -> list[dict]:
    crop = dict(crop=tuple(args.crop), random_crop=True) if args.crop else {}
    env = EventFlowEnv(args.data, window_size=args.window_size, compute_reward=False, **crop)
    out = []
    for seq in range(0, len(env.sources), max(1, len(env.sources) // args.sequences)):
        _, info = env.reset(seed=seq, options={"sequence": seq})
        for _ in range(args.per_sequence):
            out.append(info)
            _, _, _, truncated, info = env.step(np.zeros(env.action_space.shape, np.float32))
            if truncated:
                break
    return out


def batch_of(infos: list[dict]) -> tuple[EventBatch, torch.Tensor, torch.Tensor]:
    b = EventBatch.from_windows([i["window"] for i in infos])
    gt = torch.from_numpy(np.stack([i["flow_gt"] for i in infos]))
    valid = torch.from_numpy(np.stack([i["flow_gt_valid"] for i in infos]))
    return b, gt, valid


def scale(args) -> None:
    rows = []
    for info in windows(args):
        b, gt, _ = batch_of([info])
        kw = dict(flow_scaling=args.flow_scaling)
        zero = zero_flow_loss(gt, b, PLAIN_RULE, **kw)
        rows.append([window_loss(c * gt, b, PLAIN_RULE, zero_flow=zero.per_sample, **kw).loss.item() / zero.loss.item()
                     for c in SCALES])
    r = np.array(rows)
    print(f"dt = {args.window_size}: {len(r)} windows; loss / zero-flow loss for c x truth, c = {SCALES}:")
    print("  mean   " + " ".join(f"{v:.4f}" for v in r.mean(0)))
    print(f"  truth beats zero flow in {100 * (r[:, 2] < 1).mean():.0f} % of windows; "
          f"best c counts {np.bincount(r.argmin(1), minlength=len(SCALES)).tolist()}")


def border(args) -> None:
    """Truth / zero flow without the rule, with it, and with it ramped over --ramps pixels; and
    the best constant action (--game-magnitudes x 8 directions) / zero flow under each rule."""
    ramps = [0.0] + list(args.ramps)
    angles = np.arange(8) * np.pi / 4
    rows, games = [], []
    for info in windows(args):
        b, gt, _ = batch_of([info])
        reference = zero_flow_loss(gt, b, NO_RULE, flow_scaling=args.flow_scaling)
        kw = dict(flow_scaling=args.flow_scaling, zero_flow=reference.per_sample)
        zero = reference.loss.item()
        plain = window_loss(gt, b, NO_RULE, **kw)
        row = [plain.loss.item() / zero]
        row += [window_loss(gt, b, LossSpec(border_ramp=r), **kw).loss.item() / zero for r in ramps]
        rows.append(row + [1 - plain.components["kept"].item()])
        game = []  # per rule and magnitude: the best of 8 directions
        for r in [None] + ramps:  # None: no rule
            for m in args.game_magnitudes:
                best = np.inf
                for a in angles:
                    const = torch.zeros_like(gt)
                    const[:, 0], const[:, 1] = m * np.cos(a), m * np.sin(a)
                    rule = NO_RULE if r is None else LossSpec(border_ramp=r)
                    best = min(best, window_loss(const, b, rule, **kw).loss.item() / zero)
                game.append(best)
        games.append(game)
    r = np.array(rows)
    g = np.array(games).reshape(len(r), len(ramps) + 1, len(args.game_magnitudes))
    where = f"{args.crop[0]}x{args.crop[1]} crops" if args.crop else "whole frames"
    print(f"dt = {args.window_size}, {where}, {len(r)} windows; share of the truth's splat weight dropped "
          f"{r[:, -1].mean():.4f}")
    print("  best constant action / zero flow (mean over windows), by magnitude: "
          + " ".join(f"{m:g}" for m in args.game_magnitudes))
    print(f"  {'no rule':<19} truth / zero {r[:, 0].mean():.4f} (truth wins {100 * (r[:, 0] < 1).mean():.0f} %); "
          "constant: " + " ".join(f"{v:.3f}" for v in g[:, 0].mean(0)))
    for j, ramp in enumerate(ramps):
        name = "rule, no ramp" if ramp == 0 else f"rule, ramp {ramp:g} px"
        print(f"  {name:<19} truth / zero {r[:, j + 1].mean():.4f} (truth wins {100 * (r[:, j + 1] < 1).mean():.0f} %); "
              "constant: " + " ".join(f"{v:.3f}" for v in g[:, j + 1].mean(0)))


def teacher(args) -> None:
    args.steps = 40 if args.steps is None else args.steps
    b, gt, valid = batch_of(windows(args))
    H, W = gt.shape[-2:]
    mask = valid & event_pixel_mask(b.x, b.y, b.mask, H, W)
    start = time.perf_counter()
    flow = contrast_maximisation_flow(b, H, W, grids=args.grids, steps=args.steps, lr=args.lr,
                                      flow_scaling=args.flow_scaling,
                                      weights=dataclasses.replace(CMAX_WEIGHTS, lambda_2=args.lambda_2))
    seconds = time.perf_counter() - start
    aee = (flow - gt).norm(dim=1)[mask].mean().item()
    zero = gt.norm(dim=1)[mask].mean().item()
    cos = F.cosine_similarity(flow, gt, dim=1)[mask].mean().item()
    print(f"dt = {args.window_size}: {gt.shape[0]} windows {H}x{W}, grids {args.grids} x {args.steps} steps: "
          f"AEE {aee:.3f} vs zero flow {zero:.3f} ({aee / zero:.2f}x), cos {cos:.2f}, {seconds:.1f} s")


def targets(args) -> None:
    from agents.teacher import TeacherTargets

    if not args.cache:
        raise SystemExit("targets: pass --cache FILE (made by scripts/teacher_targets.py)")
    cache = TeacherTargets(args.cache)
    for k in cache.config["window_sizes"]:
        env = EventFlowEnv(args.data, window_size=k, compute_reward=False)
        err = zero = cos = count = 0.0
        for seq in range(len(env.sources)):
            _, info = env.reset(options={"sequence": seq})
            while True:
                b, gt, valid = batch_of([info])
                mask = (valid & event_pixel_mask(b.x, b.y, b.mask, *gt.shape[-2:]))[0]
                flow = cache.target(info["sequence"], info["window"].t_start, info["window"].t_end)
                err += (flow - gt[0]).norm(dim=0)[mask].sum().item()
                zero += gt[0].norm(dim=0)[mask].sum().item()
                cos += F.cosine_similarity(flow, gt[0], dim=0)[mask].sum().item()
                count += mask.sum().item()
                _, _, _, truncated, info = env.step(np.zeros(env.action_space.shape, np.float32))
                if truncated:
                    break
        print(f"dt = {k}: {len(env.sources)} recordings, AEE {err / count:.3f} vs zero flow {zero / count:.3f} "
              f"({err / zero:.2f}x), cos {cos / count:.2f} (pixel-weighted over all windows)")


def overfit(args) -> None:
    args.steps = 150 if args.steps is None else args.steps
    from agents import make_model
    from agents.learner import init_flow_heads

    crop = dict(crop=tuple(args.crop), random_crop=True) if args.crop else {}
    env = EventFlowEnv(args.data, window_size=args.window_size, compute_reward=False, observations=("voxel_grid",), **crop)
    xs, infos = [], []
    for seq in range(0, len(env.sources), max(1, len(env.sources) // args.sequences)):
        env.reset(seed=seq, options={"sequence": seq})
        obs, _, _, _, info = env.step(np.zeros(env.action_space.shape, np.float32))
        xs.append(obs["voxel_grid"])
        infos.append(info)
    x = torch.from_numpy(np.stack(xs))
    b, gt, valid = batch_of(infos)
    H, W = gt.shape[-2:]
    mask = valid & event_pixel_mask(b.x, b.y, b.mask, H, W)
    zero = zero_flow_loss(gt, b, PLAIN_RULE, flow_scaling=args.flow_scaling)
    kw = dict(flow_scaling=args.flow_scaling, zero_flow=zero.per_sample)  # the border rule's reference
    truth = window_loss(gt, b, PLAIN_RULE, **kw).loss.item() / zero.loss.item()
    torch.manual_seed(0)
    model = make_model("ev-flownet", width="cpu", flow_scaling=args.flow_scaling, in_channels=x.shape[1])
    init_flow_heads(model, 0.01)
    optimizer = torch.optim.Adam(model.parameters(), lr=1e-3)
    aee_zero = gt.norm(dim=1)[mask].mean().item()
    print(f"{gt.shape[0]} windows {H}x{W}, dt = {args.window_size}; the true flow's loss / zero flow's: {truth:.3f}")
    for step in range(args.steps + 1):
        flows, _ = model(x, None)
        out = window_loss(flows, b, PLAIN_RULE, **kw)
        if step % 30 == 0:
            f = flows[-1].detach()
            print(f"  step {step:>3}: loss / zero {out.loss.item() / zero.loss.item():.3f}, "
                  f"AEE {(f - gt).norm(dim=1)[mask].mean().item():.2f} (zero flow {aee_zero:.2f}), "
                  f"cos {F.cosine_similarity(f, gt, dim=1)[mask].mean().item():.2f}", flush=True)
        optimizer.zero_grad()
        out.loss.backward()
        optimizer.step()


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("what", choices=["scale", "border", "teacher", "overfit", "targets"])
    p.add_argument("--data", default="synthetic-train")
    p.add_argument("--window-size", type=int, default=1, help="frames per window")
    p.add_argument("--crop", type=int, nargs=2, default=[64, 64], help="random crop H W ('0 0': whole frames)")
    p.add_argument("--sequences", type=int, default=16)
    p.add_argument("--per-sequence", type=int, default=3)
    p.add_argument("--flow-scaling", type=float, default=32.0)
    p.add_argument("--grids", type=int, nargs="+", default=[4, 8])
    p.add_argument("--steps", type=int, default=None, help="teacher: Adam steps per level (40); overfit: steps (150)")
    p.add_argument("--lr", type=float, default=0.05)
    p.add_argument("--lambda-2", type=float, default=CMAX_WEIGHTS.lambda_2)
    p.add_argument("--ramps", type=float, nargs="*", default=[2.0, 4.0, 8.0, 16.0],
                   help="border: ramp lengths (pixels) to compare with the plain rule")
    p.add_argument("--game-magnitudes", type=float, nargs="*", default=[2, 4, 8, 16, 32, 64, 128, 1000],
                   help="border: constant actions tried (pixels per window, 8 directions each)")
    p.add_argument("--cache", default=None, help="targets: the teacher-target file")
    p.add_argument("--threads", type=int, default=None)
    args = p.parse_args(argv)
    if args.crop == [0, 0]:
        args.crop = None
    if args.threads:
        torch.set_num_threads(args.threads)
    {"scale": scale, "border": border, "teacher": teacher, "overfit": overfit, "targets": targets}[args.what](args)
    return 0


if __name__ == "__main__":
    sys.exit(main())
