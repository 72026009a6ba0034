"""The paper's ablations (Tables 2-4 layout) with the project's recipe, at one budget for all.

Each configuration (EV-MGRFlowNet and its ablations without ST-ConvGRU / prior flows / both;
EV-MGRFlowNet, ConvGRU-EV-FlowNet and XLIF-EV-FlowNet with L_HMC and with L_AT; EV-FlowNet with
L_HMC) trains a teacher stage on cached contrast-maximisation targets of its loss, then a
fine-tuning stage on the loss itself; is evaluated on synthetic-test and synthetic-stress at
dt = 1 and 4; and its parameters, arithmetic and time per window are measured. Everything is in
evflow_cli/ablations.py; this is the command line.

  python scripts/ablations.py                       # the documented budget (docs/ablations/README.md)
  nohup python scripts/ablations.py > runs/ablations.log 2>&1 &      # in the background
  python scripts/ablations.py --tables-only         # regenerate the tables from the rows so far

Writes RECORD/rows.jsonl (a row per finished configuration and seed, at once), RECORD/tables.md,
RECORD/curves/<configuration>.png (validation AEE against step) and the tables into --report.
RECORD (docs/ablations) is in the repository: commit it after rows finish (this command never
writes to git; ``python tools/campaign_commit.py --ablations`` does) and finished rows survive a
new machine. The teacher targets, once solved, are kept there too (RECORD/targets/<loss>.h5): a
new machine starts training at once, and so are the stages in progress (RECORD/unfinished/*.pt,
slim like a campaign's state, under 12 MB each): a fresh clone continues a stopped stage.
Checkpoints and evaluations stay in --out.
Resumable: rerun the same command; finished configurations are skipped, a killed one continues
from its checkpoint (SIGTERM / Ctrl-C stop a stage cleanly).
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import signal
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

from agents.options import (
    DeviceOptions,
    command_parser,
    default_device,
    non_negative_int,
    option,
    options_from_args,
    positive_int,
)
from evflow_cli.ablations import CONFIGURATIONS, AblationRunner, Budget, RunnerStopped

ROOT = Path(__file__).resolve().parents[2]  # the checkout


@dataclass
class AblationsOptions(DeviceOptions):
    """Which configurations scripts/ablations.py runs, at what budget, and where the rows go."""

    out: str = "runs/ablations"
    """run folder (targets, checkpoints, evaluations)"""
    record: str = "docs/ablations"
    """folder of the rows, budget, tables and curves (in the repository: commit it)"""
    report: str = "docs/ablations/README.md"
    """file whose ablation markers get the tables ('' for none)"""
    seeds: list[int] = option(default_factory=lambda: [0, 1, 2], type=non_negative_int)
    """the full model's seeds; the first is every configuration's, the second the adaptive one's"""
    only: list[str] | None = option(None, choices=list(CONFIGURATIONS))
    """run only these configurations"""
    teacher_steps: int = option(Budget.teacher_steps, type=non_negative_int)
    """teacher stage steps (the documented budget)"""
    finetune_steps: int = option(Budget.finetune_steps, type=non_negative_int)
    """fine-tuning stage steps (0: none)"""
    eval_windows: int | None = option(None, type=positive_int)
    """windows per evaluated sequence (default: all)"""
    targets_hmc: str | None = None
    """existing L_HMC teacher targets of the training split to reuse"""
    targets_at: str | None = None
    """existing L_AT teacher targets (lambda_1 = 0) to reuse"""
    tables_only: bool = False
    """only regenerate the tables and curves from the rows"""


def build_parser() -> argparse.ArgumentParser:
    return command_parser(AblationsOptions, __doc__, defaults={"device": default_device()})


def run_stage(cmd: list[str], env: dict | None = None) -> None:
    """Run a stage's process to its end; a SIGTERM or SIGINT that reaches the runner while it runs is
    passed on to it (train.py then saves and returns, and the runner stops after it, keeping the
    stage), instead of ending the runner alone and leaving the stage training on unseen."""
    child = subprocess.Popen(cmd, env=env)

    def forward(signum, _frame):
        if child.poll() is None:
            child.send_signal(signal.SIGTERM)

    previous = {sig: signal.signal(sig, forward) for sig in (signal.SIGTERM, signal.SIGINT)}
    try:
        code = child.wait()
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    if code != 0:
        raise subprocess.CalledProcessError(code, cmd)


def main(argv=None) -> int:
    args = options_from_args(AblationsOptions, build_parser().parse_args(argv))
    args.set_threads()
    budget = dataclasses.replace(Budget(), teacher_steps=args.teacher_steps, finetune_steps=args.finetune_steps,
                                 eval_windows=args.eval_windows)
    targets = {loss: path for loss, path in (("hmc", args.targets_hmc), ("at", args.targets_at)) if path}

    def written(files: list[Path]) -> None:
        print(f"[ablations] written: {', '.join(str(f) for f in files if f.exists())} "
              f"(commit them: python tools/campaign_commit.py --ablations)", flush=True)

    def train(argv: list[str]) -> None:
        # each stage in its own process (as ship.py does): a stage run inside the runner's process
        # did not learn (docs/history/2026-12-02-round-10.md), the same options in a process of their own did
        env = {**os.environ, **({"OMP_NUM_THREADS": str(args.threads)} if args.threads else {})}
        run_stage([sys.executable, str(ROOT / "scripts" / "train.py"), *argv], env)

    runner = AblationRunner(args.out, budget, train, seeds=tuple(args.seeds), only=args.only,
                            device=args.device, targets=targets, record=args.record, on_row=written,
                            on_targets=written)
    report = Path(args.report) if args.report else None
    if args.tables_only:
        print(runner.write_outputs(report))
        return 0
    try:
        runner.run(report)
    except RunnerStopped as stop:
        print(f"[ablations] {stop}", file=sys.stderr)
        return 3
    print(runner.write_outputs(report))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
