#!/usr/bin/env python
"""How much of a network's error one motion per window could remove, and how much of the true
flow one motion per window holds: oracle corrections fitted with the ground truth, per window.

    python tools/global_headroom.py --data ../shared/devval --dt 1 4 --out runs/diagnosis/headroom.json

Per window, on the AEE's own pixels (events in the window, valid ground truth), with the network
run as scripts/evaluate.py runs it one pass (whole frames, recurrent state carried):

- ``net``: the network's AEE;
- ``+translation``: after adding the one translation that best explains its error (the
  component-wise median of truth - prediction, which minimises the L1 error per component);
- ``+affine``: after adding the affine field (u, v each a + b x + c y) that fits its error best in
  least squares: what a perfect global head added to this network could reach;
- ``truth affine``: the affine field fitted to the ground truth itself, no network: how much
  of the true motion one affine motion per window explains (independently moving objects,
  depth and perspective are what it misses);
- ``own affine``: the affine field fitted to the network's own flow (no ground truth): smoothing
  the network into one motion, something a user could do.

Columns are means over each sequence's windows (as scripts/evaluate.py averages), then over
sequences. The corrections see the ground truth: they bound what a global correction could do,
they are not methods.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402
import torch  # noqa: E402

from agents.evaluation import evaluate  # noqa: E402
from envs.representations import event_mask  # noqa: E402
from tools._report import write_report  # noqa: E402

COLUMNS = {"aee": "net", "aee_translation": "+translation", "aee_affine": "+affine",
           "aee_truth_affine": "truth affine", "aee_own_affine": "own affine"}


def affine_basis(xs: np.ndarray, ys: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """(N, 3) columns 1, x, y with x and y centred and scaled to the frame (conditioning only)."""
    height, width = size
    return np.stack([np.ones(len(xs)), xs / width - 0.5, ys / height - 0.5], axis=1)


def headroom(pred: np.ndarray, gt: np.ndarray, mask: np.ndarray) -> dict[str, float]:
    """The columns of the module docstring for one window. pred, gt: (2, H, W) pixels (pred
    already in the ground truth's interval); mask: (H, W) bool, the scored pixels (at least 3)."""
    ys, xs = np.nonzero(mask)
    if len(ys) < 3:
        raise ValueError(f"headroom needs at least 3 scored pixels, got {len(ys)}")
    p, g = pred[:, ys, xs].T.astype(np.float64), gt[:, ys, xs].T.astype(np.float64)  # (N, 2)
    basis = affine_basis(xs, ys, mask.shape)

    def aee(flow: np.ndarray) -> float:
        return float(np.linalg.norm(g - flow, axis=1).mean())

    def fitted(target: np.ndarray) -> np.ndarray:
        coef, *_ = np.linalg.lstsq(basis, target, rcond=None)
        return basis @ coef

    return {"aee": aee(p), "aee_translation": aee(p + np.median(g - p, axis=0)),
            "aee_affine": aee(p + fitted(g - p)), "aee_truth_affine": aee(fitted(g)),
            "aee_own_affine": aee(fitted(p))}


def make_scorer():
    """evaluate()'s scorer hook: the usual AEE pixels, every column of :func:`headroom`."""
    def scorer(reader):
        def score(flow, info, window, size, dt_ratio):
            scored = event_mask(window.events, size) & info["flow_gt_valid"]
            if scored.sum() < 3:
                return {"aee": float("nan"), "n_pixels": 0}, scored
            return {**headroom(flow * dt_ratio, info["flow_gt"], scored), "n_pixels": int(scored.sum())}, scored
        return score
    return scorer


def load(model: str | None):
    from evflow_cli.predict import load_policy

    policy, provenance = load_policy(model)
    return policy, provenance.get("name") or provenance.get("path") or model


def table(title: str, per_sequence: dict[str, dict[str, float]]) -> str:
    lines = [f"**{title}**", "", "| sequence | " + " | ".join(COLUMNS.values()) + " |",
             "|---|" + "---:|" * len(COLUMNS)]
    for name, row in per_sequence.items():
        lines.append(f"| {name} | " + " | ".join(f"{row[k]:.3f}" for k in COLUMNS) + " |")
    means = {k: float(np.nanmean([row[k] for row in per_sequence.values()])) for k in COLUMNS}
    lines.append("| **mean over sequences** | " + " | ".join(f"{means[k]:.3f}" for k in COLUMNS) + " |")
    return "\n".join(lines)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", default="../shared/devval", help="recordings (file or folder) or a split name")
    p.add_argument("--model", default=None,
                   help="a shipped name or a checkpoint file (default: the shipped default)")
    p.add_argument("--dt", type=int, nargs="+", default=[1, 4], help="ground-truth intervals per window")
    p.add_argument("--max-windows", type=int, default=None, help="per sequence (default: all)")
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--out", default="runs/diagnosis/headroom.json", help="JSON path (the tables also to .md)")
    args = p.parse_args(argv)
    if any(dt < 1 for dt in args.dt):
        p.error(f"--dt: ground-truth intervals must be >= 1, got {args.dt}")
    torch.set_num_threads(args.threads)
    os.environ.setdefault("OMP_NUM_THREADS", str(args.threads))
    policy, name = load(args.model)
    report, tables = {"model": name, "data": args.data, "dt": {}}, []
    for dt in args.dt:
        rows = evaluate(policy, args.data, window="frames", window_size=dt, max_windows=args.max_windows,
                        progress=False, scorer_fn=make_scorer())
        per_sequence = {r.name: {k: r.mean(k) for k in COLUMNS} for r in rows if r.windows}
        if not per_sequence:
            raise SystemExit(f"{args.data}: no window with ground truth and events at dt = {dt}")
        report["dt"][f"dt{dt}"] = per_sequence
        tables.append(table(f"{name} on {args.data}, dt = {dt}, AEE (px)", per_sequence))
        print(tables[-1] + "\n", flush=True)
    write_report(args.out, report, "\n\n".join(tables))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
