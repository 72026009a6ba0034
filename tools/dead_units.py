#!/usr/bin/env python
"""Which ReLU channels of a network never fire: per layer that ends in a ReLU (conv_down, conv_up,
the residual blocks, the deep memory's conv_up), the channels whose output is zero on every pixel
of every window of a data set, and the share of all its outputs that are zero.

    python tools/dead_units.py --model runs/ablations/mgr-hmc-s1/teacher/checkpoint.pt --data ../shared/devval
    python tools/dead_units.py --model ev-mgrflownet-cpu-derived-cycle2 --data synthetic-test --max-windows 5
    python tools/dead_units.py --watch runs/ablations/mgr-hmc-s1/teacher/checkpoint.pt --steps 700 --lr 3e-4

``--watch RUN_CHECKPOINT`` trains a fresh network with that run's stored configuration (its data,
loss, schedule and seed; ``--lr`` and ``--seed`` may change), in memory, and prints every ``--every``
updates how many channels of the ``--layers`` fired on none of those updates' windows, beside the
training loss over zero flow's: the step where a layer dies.

A channel that never fires passes no gradient either: once every channel of a layer is dead
(``64 / 64``), nothing behind that layer can learn again or reach the flow. In EV-MGRFlowNet the
decoder's first stage (``decoder.upsamples.0``) is the only way from the residual module and
the deepest encoder level to the flow, and ``deep_memory_up`` the only way the deepest state
reaches the ST-ConvGRU. A model is a shipped name or a checkpoint file (a run's ``checkpoint.pt``).
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import torch  # noqa: E402

from agents.dormant import RELU_LAYERS, FiringRecord, relu_layers  # noqa: E402
from agents.evaluation import evaluate  # noqa: E402
from tools._report import add_model_options, check_model_options, load_named_policy, write_report  # noqa: E402


def dead_units(policy, data, dt: int = 1, max_windows: int | None = 10) -> dict[str, dict]:
    """:meth:`FiringRecord.summary` of ``policy``'s network (``policy.model``) rolled through
    ``data`` as scripts/evaluate.py rolls it (windows of ``dt`` ground-truth intervals)."""
    record = FiringRecord(policy.model)
    if not record.handles:
        raise ValueError(f"{type(policy.model).__name__}: no ReLU layer to watch (layers of the kinds "
                         f"{', '.join(kind.__name__ for kind in RELU_LAYERS)})")
    try:
        evaluate(policy, data, window="frames", window_size=dt, max_windows=max_windows, progress=False)
    finally:
        record.close()
    if not record.fired:
        raise ValueError(f"{data}: no window ran through the network at dt = {dt}")
    return record.summary()


def watch(checkpoint: str | os.PathLike, steps: int, every: int = 25, layers: tuple[str, ...] = (),
          lr: float | None = None, seed: int | None = None, echo=print) -> list[dict]:
    """Train a fresh network with the configuration stored in a training checkpoint (overriding
    ``lr`` and ``seed`` where given) for ``steps`` updates, on CPU, keeping nothing; every
    ``every`` updates one line (echoed and returned): the step, the loss over zero flow's over
    those updates, and per layer of ``layers`` (default: every ReLU layer) the channels that fired
    on none of their windows."""
    import dataclasses

    from agents.checkpoint import load_checkpoint
    from agents.learner import Learner
    from evflow_cli.commands.train import stored_config

    stored = load_checkpoint(checkpoint).get("config")
    if not stored:
        raise ValueError(f"{checkpoint}: no training configuration stored (a training run's checkpoint.pt is needed)")
    changes = {k: v for k, v in (("lr", lr), ("seed", seed)) if v is not None}
    cfg = dataclasses.replace(stored_config(stored), device="cpu", **changes)
    learner = Learner(cfg)
    names = [name for name, _ in relu_layers(learner.policy.model)]
    unknown = sorted(set(layers) - set(names))
    if unknown:
        learner.close()
        raise ValueError(f"--layers: {', '.join(unknown)} not ReLU layers of {cfg.model}; they are {', '.join(names)}")
    lines, record, loss, zero = [], FiringRecord(learner.policy.model), 0.0, 0.0
    try:
        for step in range(1, steps + 1):
            stats = learner.update()
            loss += stats["loss"]
            zero += stats.get("zero_flow_teacher", stats["zero_flow_loss"])
            if step % every == 0 or step == steps:
                summary = record.summary()
                line = {"step": learner.step, "loss_over_zero": loss / max(zero, 1e-12),
                        **{name: summary[name]["dead"] for name in (layers or names)}}
                echo(f"step {line['step']}: loss / zero flow's {line['loss_over_zero']:.3f}; silent channels "
                     + ", ".join(f"{name} {summary[name]['dead']}/{summary[name]['channels']}" for name in (layers or names)))
                lines.append(line)
                record.close()
                record, loss, zero = FiringRecord(learner.policy.model), 0.0, 0.0
    finally:
        record.close()
        learner.close()
    return lines


def table(title: str, summary: dict[str, dict]) -> str:
    lines = [f"**{title}**", "", "| layer | dead channels | zero outputs |", "|---|---:|---:|"]
    for name, row in summary.items():
        lines.append(f"| {name} | {row['dead']} / {row['channels']} | {100 * row['zero_share']:.1f} % |")
    return "\n".join(lines)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_model_options(p, max_windows=10, out="runs/diagnosis/dead_units.json")
    w = p.add_argument_group("watching a run's configuration train (--watch)")
    w.add_argument("--watch", default=None, metavar="RUN_CHECKPOINT",
                   help="train its stored configuration afresh and report the layers' silent channels as it goes")
    w.add_argument("--steps", type=int, default=700, help="updates to watch")
    w.add_argument("--every", type=int, default=25, help="updates per line")
    w.add_argument("--lr", type=float, default=None, help="peak step size (default: the run's)")
    w.add_argument("--seed", type=int, default=None, help="seed (default: the run's)")
    w.add_argument("--layers", nargs="+", default=["decoder.upsamples.0", "deep_memory_up"],
                   help="layers to report (default: EV-MGRFlowNet's decoder first stage and deep memory)")
    args = p.parse_args(argv)
    check_model_options(p, args)
    torch.set_num_threads(args.threads)
    if args.watch:
        if args.steps < 1 or args.every < 1:
            p.error(f"--steps and --every must be >= 1, got {args.steps} and {args.every}")
        watch(args.watch, args.steps, args.every, tuple(args.layers), args.lr, args.seed)
        return 0
    policy, name = load_named_policy(args.model)
    summary = dead_units(policy, args.data, args.dt, args.max_windows or None)
    text = table(f"{name} on {args.data}, dt = {args.dt}: ReLU channels that never fire", summary)
    print(text)
    write_report(args.out, {"model": name, "data": args.data, "dt": args.dt, "max_windows": args.max_windows,
                            "layers": summary}, text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
