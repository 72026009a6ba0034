#!/usr/bin/env python
"""How much a recurrent network gains from its state: per-window AEE with the state carried from
window to window (as scripts/evaluate.py runs it) against the same network reset before every
window, by the window's place in its sequence.

    python tools/state_use.py --model ev-mgrflownet-cpu-derived-cycle2 --data ../shared/devval --dt 1 \\
        --max-windows 40 --out runs/diagnosis/state_use.json

Columns, per sequence (means over its windows in each range of places, first window = 0): the
first window (no state in either run, so both columns agree), windows 1-4, 5-14 and 15 on.
A network whose per-window estimate is weak is weak from the first window on; one that leans on
its state differs between the two runs from window 1 on. A model is a shipped name or a
checkpoint file (a run's ``checkpoint.pt``).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402
import torch  # noqa: E402

from agents.evaluation import evaluate  # noqa: E402
from envs.representations import event_mask  # noqa: E402
from losses import flow_error  # noqa: E402
from tools._report import add_model_options, check_model_options, load_named_policy, write_report  # noqa: E402

#: (label, first place, end place or None) of the table's columns
PLACES = (("first", 0, 1), ("1-4", 1, 5), ("5-14", 5, 15), ("15+", 15, None))


class ResetEveryWindow:
    """A flow policy that resets ``policy`` before each window: the same network without memory."""

    def __init__(self, policy) -> None:
        self.policy = policy

    def __getattr__(self, name: str):  # the env's questions (observation options...) go to the policy
        return getattr(self.policy, name)

    def reset(self, mask=None) -> None:
        self.policy.reset()

    def act(self, obs, window=None) -> np.ndarray:
        self.policy.reset()
        return self.policy.act(obs, window)


def per_window_aee(policy, data, dt: int, max_windows: int | None) -> dict[str, list[float]]:
    """Each sequence's per-window AEE, in order (NaN for a window without scored pixels), on the
    AEE's usual pixels (events in the window, valid ground truth)."""
    found: list[list[float]] = []

    def scorer(reader):
        aees: list[float] = []
        found.append(aees)

        def score(flow, info, window, size, dt_ratio):
            scored = event_mask(window.events, size) & info["flow_gt_valid"]
            err = flow_error(flow, info["flow_gt"], info["flow_gt_valid"], scored, dt_ratio=dt_ratio)
            aees.append(err["aee"] if err["n_pixels"] else float("nan"))
            return err, scored
        return score

    rows = evaluate(policy, data, window="frames", window_size=dt, max_windows=max_windows, progress=False,
                    scorer_fn=scorer)
    return {row.name: aees for row, aees in zip(rows, found) if row.windows}


def by_place(aees: list[float]) -> dict[str, float]:
    """Mean AEE over each range of :data:`PLACES` (NaN where the sequence has no such window)."""
    values = np.asarray(aees, dtype=np.float64)
    out = {}
    for label, start, end in PLACES:
        part = values[start:end]
        part = part[np.isfinite(part)]
        out[label] = float(part.mean()) if part.size else float("nan")
    return out


def table(title: str, carried: dict[str, list[float]], reset: dict[str, list[float]]) -> str:
    labels = [label for label, _, _ in PLACES]
    lines = [f"**{title}**", "",
             "| sequence | windows | " + " | ".join(f"carried {x}" for x in labels) + " | "
             + " | ".join(f"reset {x}" for x in labels) + " | carried all | reset all |",
             "|---|---:|" + "---:|" * (2 * len(labels) + 2)]
    means = {"carried": [], "reset": []}
    for name in carried:
        a, b = by_place(carried[name]), by_place(reset[name])
        whole = [float(np.nanmean(carried[name])), float(np.nanmean(reset[name]))]
        means["carried"].append(whole[0])
        means["reset"].append(whole[1])
        cells = [a[x] for x in labels] + [b[x] for x in labels] + whole
        lines.append(f"| {name} | {len(carried[name])} | " + " | ".join(f"{v:.3f}" for v in cells) + " |")
    cells = ["mean over sequences", "", *[""] * (2 * len(labels)), f"{np.mean(means['carried']):.3f}",
             f"{np.mean(means['reset']):.3f}"]
    lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_model_options(p, max_windows=40, out="runs/diagnosis/state_use.json")
    args = p.parse_args(argv)
    check_model_options(p, args)
    torch.set_num_threads(args.threads)
    policy, name = load_named_policy(args.model)
    windows = args.max_windows or None
    carried = per_window_aee(policy, args.data, args.dt, windows)
    reset = per_window_aee(ResetEveryWindow(policy), args.data, args.dt, windows)
    if not carried:
        raise SystemExit(f"{args.data}: no window with ground truth and events at dt = {args.dt}")
    text = table(f"{name} on {args.data}, dt = {args.dt}, AEE (px) by the window's place", carried, reset)
    print(text)
    write_report(args.out, {"model": name, "data": args.data, "dt": args.dt, "carried": carried, "reset": reset}, text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
