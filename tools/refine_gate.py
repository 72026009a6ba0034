#!/usr/bin/env python
"""Does the drop of L_HMC under test-time refinement say where the refinement helps?

For the first windows of every sequence of a split (dt = 1 and 4), the shipped network's flow
and its refinement (``RefinedPolicy``, the network's flow fed back as in evaluation) are scored
on the window's L_HMC (the env's reward loss) and on the AEE to the ground truth (pixels with
events). Prints the mean AEE of the network, the refinement, zero flow and of the acceptance
gate (``RefinedPolicy(accept=A)``: the refinement kept only where the loss falls by >= A) for
several A, from the same windows, so one pass prices every threshold.

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

    from agents.cmax import RefinedPolicy
    from agents.policy import RecurrentPolicy
    from envs.dataset import resolve_data
    from envs.env import EventFlowEnv
    from envs.representations import EventView, event_mask
    from losses import EventBatch, flow_error, hmc_loss

    network = RecurrentPolicy.from_pretrained(pretrained)
    solver, steps, prior = spec.split(":")
    refine = RefinedPolicy(network, solver=solver, steps=int(steps), prior_weight=float(prior))
    rows = []
    for dt in dts:
        for index in range(len(resolve_data(data))):
            env = EventFlowEnv(data, window="frames", window_size=dt, compute_reward=False, sequences=[index],
                               observations=(network.input_key, "count_image"), voxel_bins=network.voxel_bins)
            obs, info = env.reset(options={"sequence": 0})
            network.reset()
            size = (env.height, env.width)
            for w in range(max_windows):
                window = {**info["events"], "t_start": info["t_start"], "t_end": info["t_end"]}
                flow = network.act(obs)  # the network's own flow drives its state, as in evaluation
                if len(window["t"]) and "flow_gt" in info:
                    refined = refine.settings.solve(window, size, base=flow, device="cpu")
                    flows = (flow, refined, np.zeros_like(flow))
                    batch = EventBatch.from_windows([window])
                    with torch.no_grad():
                        losses = [float(hmc_loss(torch.from_numpy(f)[None], batch, flow_scaling=float(max(size))).loss)
                                  for f in flows]
                    scored = event_mask(EventView(window), size)
                    aee = [flow_error(f, info["flow_gt"], info["flow_gt_valid"], scored)["aee"] for f in flows]
                    rows.append({"dt": dt, "sequence": index, "window": w, "loss": losses, "aee": aee,
                                 "events": len(window["t"])})
                    if out is not None:
                        with out.open("a") as f:
                            f.write(json.dumps(rows[-1]) + "\n")
                obs, _, _, truncated, info = env.step(flow)
                if truncated:
                    break
            env.close()
    return rows


def table(rows: list[dict]) -> str:
    """Mean AEE per window length: network, refined, zero flow, and the gate at each threshold."""
    lines = ["| dt | windows | network | refined | zero flow | " + " | ".join(f"gate {t:g}" for t in THRESHOLDS) + " |",
             "|---|---|---|---|---|" + "---|" * len(THRESHOLDS)]
    for dt in sorted({r["dt"] for r in rows}):
        part = [r for r in rows if r["dt"] == dt]
        mean = [np.mean([r["aee"][k] for r in part]) for k in range(3)]
        gated = [np.mean([r["aee"][1] if r["loss"][1] <= (1 - t) * r["loss"][0] else r["aee"][0] for r in part])
                 for t in THRESHOLDS]
        lines.append(f"| {dt} | {len(part)} | " + " | ".join(f"{v:.3f}" for v in [*mean, *gated]) + " |")
    return "\n".join(lines)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", default="synthetic-dr-val")
    p.add_argument("--pretrained", default=None, help="shipped model (default: the default one)")
    p.add_argument("--max-windows", type=int, default=5, help="per sequence")
    p.add_argument("--dt", type=int, nargs="+", default=[1, 4])
    p.add_argument("--refine", default="cmax:100:0", help="SOLVER:STEPS:PRIOR of the refinement")
    p.add_argument("--out", type=Path, default=None, help="append each window's numbers here (JSON lines)")
    p.add_argument("--from", dest="source", type=Path, default=None, help="re-tabulate such a file, solve nothing")
    args = p.parse_args(argv)
    if args.source is not None:
        rows = [json.loads(line) for line in args.source.read_text().splitlines() if line.strip()]
    else:
        import torch

        from agents.pretrained import DEFAULT_PRETRAINED

        torch.set_num_threads(1)
        rows = score_windows(args.data, args.pretrained or DEFAULT_PRETRAINED, args.max_windows, args.dt,
                             args.refine, args.out)
    print(table(rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
