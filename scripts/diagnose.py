#!/usr/bin/env python
"""Loss-landscape diagnostics on synthetic windows (no network), used in docs/results.md.

  python scripts/diagnose.py scale   --window-size 1      # L_HMC of c x ground truth, c = 0 .. 2
  python scripts/diagnose.py teacher --window-size 1      # per-window contrast maximisation vs truth

scale: for windows of the training split, the loss (with the border rule) of c x the true
flow divided by zero flow's, for c in 0.5, 0.75, 1, 1.25, 1.5, 2: the mean ratio per c, the share
of windows where the truth beats zero flow, and how often each c is the best.
teacher: ``losses.contrast_maximisation_flow`` on a batch of windows: AEE against the truth
(pixels with events and valid truth) and the cosine, beside zero flow's AEE.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402
import torch  # noqa: E402
import torch.nn.functional as F  # noqa: E402

from envs.env import EventFlowEnv  # noqa: E402
from losses import EventBatch, contrast_maximisation_flow, event_pixel_mask, hmc_loss  # noqa: E402

SCALES = (0.5, 0.75, 1.0, 1.25, 1.5, 2.0)


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
    b = EventBatch.from_windows([{**i["events"], "t_start": i["t_start"], "t_end": i["t_end"]} for i in infos])
    gt = torch.from_numpy(np.stack([i["flow_gt"] for i in infos]))
    valid = torch.from_numpy(np.stack([i["flow_gt_valid"] for i in infos]))
    return b, gt, valid


def scale(args) -> None:
    rows = []
    for info in windows(args):
        b, gt, _ = batch_of([info])
        zero = hmc_loss(torch.zeros_like(gt), b, flow_scaling=args.flow_scaling).loss.item()
        rows.append([hmc_loss(c * gt, b, flow_scaling=args.flow_scaling, border_penalty=zero).loss.item() / zero
                     for c in SCALES])
    r = np.array(rows)
    print(f"dt = {args.window_size}: {len(r)} windows; loss / zero-flow loss for c x truth, c = {SCALES}:")
    print("  mean   " + " ".join(f"{v:.4f}" for v in r.mean(0)))
    print(f"  truth beats zero flow in {100 * (r[:, 2] < 1).mean():.0f} % of windows; "
          f"best c counts {np.bincount(r.argmin(1), minlength=len(SCALES)).tolist()}")


def teacher(args) -> None:
    b, gt, valid = batch_of(windows(args))
    H, W = gt.shape[-2:]
    mask = valid & event_pixel_mask(b.x, b.y, b.mask, H, W)
    start = time.perf_counter()
    flow = contrast_maximisation_flow(b, H, W, grids=args.grids, steps=args.steps, lr=args.lr,
                                      flow_scaling=args.flow_scaling, lambda_2=args.lambda_2)
    seconds = time.perf_counter() - start
    aee = (flow - gt).norm(dim=1)[mask].mean().item()
    zero = gt.norm(dim=1)[mask].mean().item()
    cos = F.cosine_similarity(flow, gt, dim=1)[mask].mean().item()
    print(f"dt = {args.window_size}: {gt.shape[0]} windows {H}x{W}, grids {args.grids} x {args.steps} steps: "
          f"AEE {aee:.3f} vs zero flow {zero:.3f} ({aee / zero:.2f}x), cos {cos:.2f}, {seconds:.1f} s")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("what", choices=["scale", "teacher"])
    p.add_argument("--data", default="synthetic-train")
    p.add_argument("--window-size", type=int, default=1, help="frames per window")
    p.add_argument("--crop", type=int, nargs=2, default=[64, 64], help="random crop H W ('0 0': whole frames)")
    p.add_argument("--sequences", type=int, default=16)
    p.add_argument("--per-sequence", type=int, default=3)
    p.add_argument("--flow-scaling", type=float, default=32.0)
    p.add_argument("--grids", type=int, nargs="+", default=[4, 8])
    p.add_argument("--steps", type=int, default=40)
    p.add_argument("--lr", type=float, default=0.05)
    p.add_argument("--lambda-2", type=float, default=1e-2)
    p.add_argument("--threads", type=int, default=None)
    args = p.parse_args(argv)
    if args.crop == [0, 0]:
        args.crop = None
    if args.threads:
        torch.set_num_threads(args.threads)
    {"scale": scale, "teacher": teacher}[args.what](args)
    return 0


if __name__ == "__main__":
    sys.exit(main())
