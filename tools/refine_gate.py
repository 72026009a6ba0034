#!/usr/bin/env python
"""Does the drop of L_HMC under test-time refinement say where the refinement helps?

For the first windows of every sequence of a split (dt = 1 and 4), the shipped network's flow
and its refinement (``RefinedPolicy``, the network's flow fed back as in evaluation) are scored
on the window's loss as the env scores it (``losses.window_loss``: L_HMC with the border rule,
which the gate ``RefinedPolicy(accept=A)`` and the evaluation's column use), on plain L_HMC (no
border rule) and
on the AEE to the ground truth (pixels with events and valid truth). Prints the mean AEE of the
network, the refinement, zero flow and of the gate (the refinement kept only where the loss
falls by at least the fraction A) for several A, by either loss, from the same windows: one
pass prices every threshold.

    python tools/refine_gate.py --data synthetic-dr-val --max-windows 5 --out runs/refine-gate.jsonl
    python tools/refine_gate.py --from runs/refine-gate.jsonl      # the table again, nothing solved

Tune on the selection split (synthetic-dr-val), never on synthetic-stress or a test split.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

THRESHOLDS = (0.0, 0.05, 0.1, 0.15, 0.2, 0.3, 0.4)


def score_windows(data: str, pretrained: str, max_windows: int, dts: list[int], spec: str, out: Path | None):
    import torch

    from agents.policy import RecurrentPolicy
    from agents.rollout import observation_options, rollout
    from agents.wrappers import RefinedPolicy
    from envs.dataset import resolve_data
    from envs.env import EventFlowEnv
    from envs.representations import event_mask
    from losses import flow_error, hmc_loss, window_loss

    network = RecurrentPolicy.from_pretrained(pretrained)
    if spec.count(":") != 2:
        raise SystemExit(f"--refine {spec}: expected SOLVER:STEPS:PRIOR (the gate's thresholds are all priced)")
    solver, steps, prior = spec.split(":")
    refine = RefinedPolicy(network, solver=solver, steps=int(steps), prior_weight=float(prior))
    rows = []
    for dt in dts:
        for index in range(len(resolve_data(data))):
            env = EventFlowEnv(data, window="frames", window_size=dt, compute_reward=False, sequences=[index],
                               **observation_options(network))
            size = (env.height, env.width)
            # the network's own flow drives its state, as in evaluation
            for step in rollout(network, env, options={"sequence": 0}, max_windows=max_windows):
                window, info, flow, w = step.window, step.info, step.flow, step.index
                if len(window.events) and "flow_gt" in info:
                    refined = refine.settings.solve(window, size, base=flow, device="cpu")
                    flows = (flow, refined, np.zeros_like(flow))
                    batch = window.batch()
                    scale = float(max(size))
                    with torch.no_grad():
                        plain = [float(hmc_loss(torch.from_numpy(f)[None], batch, flow_scaling=scale).loss) for f in flows]
                        env_loss = [float(window_loss(torch.from_numpy(f)[None], batch, flow_scaling=scale).loss)
                                    for f in flows]
                    scored = event_mask(window.events, size)
                    errors = [flow_error(f, info["flow_gt"], info["flow_gt_valid"], scored) for f in flows]
                    if errors[0]["n_pixels"] > 0:  # no valid truth under the events: not scored (as in evaluation)
                        rows.append({"dt": dt, "sequence": index, "window": w, "env_loss": env_loss, "loss": plain,
                                     "aee": [e["aee"] for e in errors], "events": len(window.events)})
                        if out is not None:
                            with out.open("a") as f:
                                f.write(json.dumps(rows[-1]) + "\n")
            env.close()
    return rows


def table(rows: list[dict]) -> str:
    """Mean AEE per window length: network, refined, zero flow, and the gate at each threshold,
    deciding by the env's loss (``env_loss``, the gate's) and by plain L_HMC (``loss``)."""
    lines = ["| dt | gate by | windows | network | refined | zero flow | "
             + " | ".join(f"gate {t:g}" for t in THRESHOLDS) + " |", "|---|---|---|---|---|---|" + "---|" * len(THRESHOLDS)]
    for dt in sorted({r["dt"] for r in rows}):
        part = [r for r in rows if r["dt"] == dt]
        mean = [np.mean([r["aee"][k] for r in part]) for k in range(3)]
        for key, label in (("env_loss", "env loss"), ("loss", "plain L_HMC")):
            if not all(key in r for r in part):
                continue
            gated = [np.mean([r["aee"][1] if r[key][1] <= (1 - t) * r[key][0] else r["aee"][0] for r in part])
                     for t in THRESHOLDS]
            lines.append(f"| {dt} | {label} | {len(part)} | " + " | ".join(f"{v:.3f}" for v in [*mean, *gated]) + " |")
    return "\n".join(lines)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", default="synthetic-dr-val")
    p.add_argument("--pretrained", default=None, help="shipped model (default: the default one)")
    p.add_argument("--max-windows", type=int, default=5, help="per sequence")
    p.add_argument("--dt", type=int, nargs="+", default=[1, 4])
    p.add_argument("--refine", default="cmax:100:0", help="SOLVER:STEPS:PRIOR of the refinement")
    p.add_argument("--out", type=Path, default=None, help="write each window's numbers here (JSON lines, as they come)")
    p.add_argument("--from", dest="source", type=Path, default=None, help="re-tabulate such a file, solve nothing")
    args = p.parse_args(argv)
    if args.source is not None:
        rows = [json.loads(line) for line in args.source.read_text().splitlines() if line.strip()]
    else:
        import torch

        from agents.pretrained import DEFAULT_PRETRAINED

        torch.set_num_threads(1)
        if args.out is not None:
            args.out.parent.mkdir(parents=True, exist_ok=True)
            args.out.write_text("")
        rows = score_windows(args.data, args.pretrained or DEFAULT_PRETRAINED, args.max_windows, args.dt,
                             args.refine, args.out)
    print(table(rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
