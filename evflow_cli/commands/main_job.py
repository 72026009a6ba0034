"""The main job, end to end on the embedded synthetic benchmark (no files needed):

0. simulate (or read from the cache) every synthetic sequence the job needs, before anything
   is timed;
1. evaluate the shipped pretrained EV-MGRFlowNet (agents/weights/, if one ships), the same
   network stepped once per ground-truth interval (``--split dt``: at dt = 4 four steps per
   window, their flows composed; at dt = 1 the network's row again), zero flow and per-window
   contrast maximisation (no network) on the synthetic test split and the held-out stress
   split at dt = 1 and dt = 4, on the first --eval-windows windows of every sequence, and print
   the tables;
2. a short training demo of the project's recipe (--demo-minutes, default 3). The recipe has
   two stages: (1) a per-window contrast-maximisation teacher of L_HMC distilled into a
   CPU-size EV-MGRFlowNet, (2) the paper's per-window L_HMC (with the ramped border rule) on
   4-frame windows. The default demo (--demo-stage hmc) runs stage 2 from the shipped stage-1
   model (the default model) and prints the network's L_HMC as a ratio to zero flow's on the
   same training windows: it starts below 1 and falls further within a few
   minutes (docs/history/2026-11-22-round-07.md). --demo-stage teacher runs stage 1 from scratch
   instead, solving the teacher inside every update (a few minutes do not yet leave zero flow
   there). Then a quick evaluation of the demo model on the test split;
3. print the commands for the full training: the teacher's targets, solved once, then both
   stages.

Everything goes to --out (default runs/main): eval/ (table.md, results.json, pictures/),
demo/ (checkpoint, metrics.jsonl) and demo-eval/. Extra scripts/train.py options for the demo
follow `--`, e.g.  python scripts/main.py --demo-minutes 1 -- --num-envs 4
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from agents.options import (
    DeviceOptions,
    check_choices,
    command_parser,
    default_device,
    non_negative_float,
    non_negative_int,
    option,
    options_from_args,
)
from agents.pretrained import DEFAULT_PRETRAINED, list_pretrained, pretrained_info
from agents.train_config import preset_options
from evflow_cli.commands import evaluate as evaluate_command
from evflow_cli.commands import train as train_command

#: The project's recipe (docs/results.md: how far it gets; docs/history/: how it was found), as train.py
#: presets (agents.train_config.PRESETS). Stage 1: distil the per-window contrast-maximisation teacher
#: (from scratch). The full run solves the teacher once (TARGETS) and trains on the stored targets
#: (CACHED_RECIPE, preset teacher-cached); the demo of stage 1 (--demo-stage teacher) solves it
#: inside every update (RECIPE, preset teacher: no 20-minute wait).
TARGETS = ["--data", "synthetic-train", "--out", "runs/teacher-targets/train.h5"]
CACHED_RECIPE = preset_options("teacher-cached")
RECIPE = preset_options("teacher")
#: Stage 2: the paper's per-window L_HMC (the env's reward, ramped border rule), from stage 1.
HMC_STAGE = preset_options("hmc-stage")
TEACHER_MODEL = DEFAULT_PRETRAINED  # stage 1 (the cached-teacher run T3), shipped as the default
#: What step 1 evaluates, and on how many windows per sequence (all rows on the same windows).
EVAL_SPLITS = ["synthetic-test", "synthetic-stress"]
EVAL_WINDOWS = 3  # the contrast-maximisation row costs seconds per window
TRAIN_SPLIT = "synthetic-train"  # the demo's data (TrainConfig's default)


@dataclass
class MainOptions(DeviceOptions):
    """What scripts/main.py evaluates and how long its demo trains (train.py's own options for
    the demo follow ``--``)."""

    demo_minutes: float = option(3.0, type=non_negative_float)
    """length of the training demo (0: skip)"""
    demo_stage: Literal["hmc", "teacher"] = "hmc"
    """hmc: stage 2 (L_HMC) from the shipped stage-1 model; teacher: stage 1 from scratch"""
    out: str = "runs/main"
    """where eval/, demo/ and demo-eval/ go"""
    eval_data: list[str] = option(default_factory=lambda: list(EVAL_SPLITS))
    """splits or recordings evaluated in step 1 (each its own table)"""
    eval_windows: int = option(EVAL_WINDOWS, type=non_negative_int)
    """windows per sequence in step 1 (0: all; the contrast-maximisation row costs seconds each)"""
    no_cmax: bool = False
    """leave the contrast-maximisation row out of step 1"""

    def __post_init__(self) -> None:
        check_choices(self)


def build_parser() -> argparse.ArgumentParser:
    return command_parser(MainOptions, __doc__, defaults={"device": default_device()})


def demo_summary(metrics: Path) -> None:
    """Print, per sixth of the demo, the recipe's loss (distance to the teacher) and the
    network's L_HMC, each as a ratio to zero flow's on the same training windows."""
    rows = [json.loads(line) for line in metrics.read_text().splitlines() if line.strip()]
    steps = [r for r in rows if "loss" in r]
    if not steps:
        return
    chunk = max(1, len(steps) // 6)
    print("[main] demo, on the same training windows (below 1 = better than zero flow):")
    if "zero_flow_teacher" in steps[0]:
        print("  teacher ratio = the recipe's loss (distance to the teacher) / zero flow's distance to it;")
    print("  L_HMC ratio = the network's L_HMC (with the border rule) / zero flow's L_HMC")
    for i in range(0, len(steps), chunk):
        part = steps[i : i + chunk]
        line = f"  steps {part[0]['step']:>4}-{part[-1]['step']:<4}"
        if all("zero_flow_teacher" in r for r in part):
            line += f"  teacher ratio {sum(r['loss'] for r in part) / sum(r['zero_flow_teacher'] for r in part):.3f}"
        ratio = sum(r.get("model_hmc", r["loss"]) for r in part) / sum(r["zero_flow_loss"] for r in part)
        print(line + f"  L_HMC ratio {ratio:.3f}")
    first, last = steps[: max(1, len(steps) // 3)], steps[-max(1, len(steps) // 3):]
    ratios = [sum(r.get("model_hmc", r["loss"]) for r in part) / sum(r["zero_flow_loss"] for r in part)
              for part in (first, last)]
    verdict = "below" if ratios[1] < 1 else "not yet below"
    print(f"  first third {ratios[0]:.3f} -> last third {ratios[1]:.3f}: the network's L_HMC is {verdict} zero flow's")


def prepare_data(splits: list[str]) -> None:
    """Simulate (or find in the disk cache) every sequence of ``splits`` before anything is
    timed, with a progress bar per split: the demo's minutes then go to training only."""
    from tqdm import tqdm

    from envs.synthetic import list_sequences, list_splits, load_sequence

    for split in dict.fromkeys(splits):
        if split not in list_splits():
            continue  # recordings on disk need no preparation
        for index in tqdm(range(len(list_sequences(split))), desc=f"[main] preparing {split} (cached)", unit="seq"):
            load_sequence(split, index).close()


def main(argv=None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    cut = argv.index("--") if "--" in argv else len(argv)
    args = options_from_args(MainOptions, build_parser().parse_args(argv[:cut]))
    args.set_threads()  # step 1 and the demo run in this process
    extra = argv[cut + 1 :]
    out = Path(args.out)
    device = ["--device", args.device]
    print("[main] 0/3 preparing the synthetic data this job uses (simulated once, then read from the cache)", flush=True)
    prepare_data([*args.eval_data, TRAIN_SPLIT] if args.demo_minutes > 0 else list(args.eval_data))

    windows = ["--max-windows", str(args.eval_windows)] if args.eval_windows else []
    rows = [] if args.no_cmax else ["--cmax"]
    for data in args.eval_data:
        name = Path(data).name
        if DEFAULT_PRETRAINED in list_pretrained():
            info = pretrained_info(DEFAULT_PRETRAINED)
            trained = info.get("budget", {}).get("optimizer_steps") or info.get("steps")  # a campaign's export: its step
            print(f"\n[main] 1/3 evaluating the shipped model {DEFAULT_PRETRAINED!r} ({info.get('date')}, "
                  f"{trained} steps), alone and once per interval, zero flow"
                  f"{'' if args.no_cmax else ' and contrast maximisation'} on {data}", flush=True)
            rows_here = ["--pretrained", DEFAULT_PRETRAINED, "--split", "dt", "--zero", *rows]
        else:
            print(f"\n[main] 1/3 no pretrained model ships in agents/weights/: zero flow on {data}", flush=True)
            rows_here = ["--zero", *rows]
        evaluate_command.main([*rows_here, "--data", data, *windows, "--out", str(out / "eval" / name),
                              "--no-progress", "--overwrite", *device])  # the job owns its --out: a rerun replaces it

    if args.demo_minutes > 0:
        stage = args.demo_stage
        if stage == "hmc" and TEACHER_MODEL not in list_pretrained():
            print(f"[main] {TEACHER_MODEL!r} does not ship: the demo runs stage 1 from scratch instead")
            stage = "teacher"
        if stage == "hmc":
            print(f"\n[main] 2/3 training demo: {args.demo_minutes:g} min of the recipe's stage 2 (per-window L_HMC) "
                  f"from the shipped stage-1 model {TEACHER_MODEL!r}", flush=True)
            recipe = [*HMC_STAGE, "--init", TEACHER_MODEL]
        else:
            print(f"\n[main] 2/3 training demo: {args.demo_minutes:g} min of the recipe's stage 1 (teacher) from scratch",
                  flush=True)
            recipe = RECIPE
        train_command.main([*recipe, "--minutes", str(args.demo_minutes), "--steps", "1000000",
                           "--out", str(out / "demo"), "--val-data", "", "--no-progress", "--overwrite", *device, *extra])
        demo_summary(out / "demo" / "metrics.jsonl")
        evaluate_command.main(["--checkpoint", str(out / "demo" / "checkpoint.pt"), "--name", "demo model", "--zero",
                              "--data", args.eval_data[0], "--window-size", "1", "4", "--max-windows", "15", "--pictures", "0",
                              "--out", str(out / "demo-eval"), "--no-progress", "--overwrite", *device])

    print("\n[main] 3/3 the full training of the recipe (resumable; --device cuda on a GPU):")
    print("  targets:  python scripts/teacher_targets.py " + " ".join(TARGETS) + "    # once, ~25 min on 2 cores")
    print("  stage 1:  python scripts/train.py --preset teacher-cached --steps 20000 --out runs/recipe")
    print("            python scripts/train.py --resume --out runs/recipe --steps 40000    # continue later")
    print("  stage 2 (optional: at CPU width and short budgets it lowered L_HMC while the flow on independent data got"
          " worse, docs/ablations/README.md; the shipped default is distilled only, docs/training.md, Campaigns):")
    print("            python scripts/train.py --preset hmc-stage --init runs/recipe/checkpoint.pt "
          "--steps 20000 --out runs/recipe-hmc")
    print("  (then optionally --window-size 1 2 3 4 --lr 1e-4 from stage 2's checkpoint for short windows;"
          " docs/results.md)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
