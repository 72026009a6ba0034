"""The main job, end to end on the embedded synthetic benchmark (no files needed):

0. simulate (or read from the cache) every synthetic sequence the job needs, before anything
   is timed;
1. evaluate the shipped pretrained EV-MGRFlowNet (agents/weights/, if one ships), the same
   network stepped once per ground-truth interval (``--split dt``: at dt = 4 four steps per
   window, their flows composed; at dt = 1 the network's row again), zero flow and per-window
   contrast maximisation (no network) on the synthetic test split and the held-out stress
   split at dt = 1 and dt = 4, on the first --eval-windows windows of every sequence, and print
   the tables;
2. a training demo that shows learning in minutes (--demo-minutes, default 4; --demo-steps, default
   1500, whichever ends first): by default (--demo-stage scratch) a small EV-FlowNet (width 8)
   from random weights, distilled on the teacher targets the default's recipe stores
   (agents/campaigns/mgr-derived/targets.h5: per-window contrast maximisation of L_HMC solved once
   on synthetic-train, no ground truth), its step size annealed along a cosine; validated on
   synthetic-test (the first 3 windows of each sequence, 1 frame) at its start, every
   --demo-val-every steps and at its end, against zero flow. It prints the curve and a verdict (the
   AEE and L_HMC at the start and the end, against zero flow's), and draws demo/learning.png
   (with the ``plots`` extra). --demo-stage teacher: the recipe's stage 1 at its own width, solving
   the teacher inside every update; hmc: the recipe's stage 2 (L_HMC) from the shipped model,
   which at this budget makes it worse (the ratio to zero flow rises: docs/training.md);
3. print the commands for the full training: the teacher's targets, solved once, then both
   stages.

Everything goes to --out (default runs/main): eval/ (table.md, results.json, pictures/),
demo/ (checkpoint, metrics.jsonl, learning.png). Extra scripts/train.py options for the demo
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
#: The demo from scratch: a small feedforward network on the stored targets of the default's
#: recipe. The recurrent EV-MGRFlowNet stays near zero flow for its first thousand-odd steps at
#: this budget; EV-FlowNet at width 8 leaves it within a few hundred (measured 2026-12-06).
DEMO_TARGETS = str(Path(__file__).resolve().parents[2] / "agents" / "campaigns" / "mgr-derived" / "targets.h5")
SCRATCH_DEMO = ["--loss", "teacher", "--teacher-cache", DEMO_TARGETS, "--teacher-pixels", "all",
                "--model", "ev-flownet", "--width", "8", "--input", "voxel_grid", "--crop", "64", "64", "--random-crop",
                "--window-size", "1", "2", "--lr", "1e-3", "--decay", "cosine", "--warmup-steps", "20",
                "--flow-scaling", "32", "--num-envs", "8", "--unroll", "1"]
VAL_DATA, VAL_WINDOWS = "synthetic-test", 3


@dataclass
class MainOptions(DeviceOptions):
    """What scripts/main.py evaluates and how long its demo trains (train.py's own options for
    the demo follow ``--``)."""

    demo_minutes: float = option(4.0, type=non_negative_float)
    """the most the training demo runs, in minutes (0: skip it)"""
    demo_steps: int = option(1500, type=non_negative_int)
    """the demo's Adam steps (its step size falls along a cosine over them); it stops at --demo-minutes if sooner"""
    demo_val_every: int = option(250, type=non_negative_int)
    """validate the demo every N steps (besides its start and end)"""
    demo_val_data: str = VAL_DATA
    """the split (or recording) the demo is validated on, the first 3 windows of each sequence"""
    demo_stage: Literal["scratch", "teacher", "hmc"] = "scratch"
    """scratch: a small EV-FlowNet from random weights on the recipe's stored teacher targets; teacher: the recipe's stage 1 from scratch, solving the teacher in every update; hmc: stage 2 (L_HMC) from the shipped model"""
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


def demo_verdict(metrics: Path, data: str = VAL_DATA) -> bool | None:
    """Print the demo's validation curve (AEE and L_HMC against zero flow's on the same windows)
    and whether it learned: its AEE at the end below its AEE at the start and below zero flow's.
    None when fewer than two validations were recorded."""
    rows = [json.loads(line) for line in metrics.read_text().splitlines() if line.strip()]
    val = [r for r in rows if "val_aee_model" in r]
    if len(val) < 2:
        print("[main] the demo recorded fewer than two validations: no curve")
        return None
    print(f"[main] the demo on {data} (the first {VAL_WINDOWS} windows of each sequence, 1 frame each):")
    print("    step   AEE px (zero flow)   L_HMC (zero flow)")
    for r in val:
        print(f"  {r['step']:>6}   {r['val_aee_model']:6.3f} ({r['val_aee_zero']:.3f})     "
              f"{r['val_hmc_model']:.4f} ({r['val_hmc_zero']:.4f})")
    first, last = val[0], val[-1]
    aee0, aee1, zero = first["val_aee_model"], last["val_aee_model"], last["val_aee_zero"]
    learned = aee1 < aee0 and aee1 < zero
    print(f"  AEE {aee0:.3f} at step {first['step']} -> {aee1:.3f} at step {last['step']} "
          f"({aee1 / zero:.2f}x zero flow's {zero:.3f}): {'below' if aee1 < aee0 else 'NOT below'} its start, "
          f"{'below' if aee1 < zero else 'NOT below'} zero flow's; L_HMC {first['val_hmc_model']:.4f} -> "
          f"{last['val_hmc_model']:.4f} (zero flow {last['val_hmc_zero']:.4f})")
    return learned


def plot_demo(metrics: Path, path: Path, data: str = VAL_DATA) -> Path | None:
    """The demo's curves as a PNG: the training loss against zero flow's, and the validation AEE
    and L_HMC against zero flow's (None, with a hint, without matplotlib)."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        print("[main] (pip install -e \".[plots]\" for the demo's picture)")
        return None
    import io

    from envs.atomic import write_atomic

    rows = [json.loads(line) for line in metrics.read_text().splitlines() if line.strip()]
    train = [r for r in rows if "loss" in r]
    val = [r for r in rows if "val_aee_model" in r]
    fig, axes = plt.subplots(1, 3, figsize=(13, 3.6))
    zero_key = "zero_flow_teacher" if train and "zero_flow_teacher" in train[0] else "zero_flow_loss"
    ratio = [r["loss"] / r[zero_key] for r in train if r.get(zero_key)]
    k = max(1, len(ratio) // 50)
    smooth = [sum(ratio[i : i + k]) / len(ratio[i : i + k]) for i in range(0, len(ratio), k)]
    axes[0].plot([train[min(i, len(train) - 1)]["step"] for i in range(0, len(ratio), k)], smooth, color="C0")
    axes[0].axhline(1.0, color="grey", ls="--", label="zero flow")
    axes[0].set(title="training loss / zero flow's", xlabel="step")
    for ax, key, title in ((axes[1], "aee", "validation AEE (px)"), (axes[2], "hmc", "validation L_HMC")):
        steps = [r["step"] for r in val]
        ax.plot(steps, [r[f"val_{key}_model"] for r in val], "o-", color="C1", label="the demo network")
        ax.plot(steps, [r[f"val_{key}_zero"] for r in val], "--", color="grey", label="zero flow")
        ax.set(title=title, xlabel="step")
    axes[0].legend(loc="upper right")
    axes[1].legend(loc="upper right")
    fig.suptitle(f"the training demo, validated on {data} (first {VAL_WINDOWS} windows per sequence)")
    fig.tight_layout()
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=90)
    plt.close(fig)
    return write_atomic(path, buffer.getvalue())


def demo_recipe(args) -> tuple[list[str], str]:
    """The train.py options of the demo stage asked for, and a line saying what it trains."""
    stage = args.demo_stage
    if stage == "scratch" and not Path(DEMO_TARGETS).is_file():
        print("[main] the stored teacher targets (agents/campaigns/mgr-derived/targets.h5) are not here (a checkout "
              "holds them): the demo solves the teacher in every update")
        stage = "teacher"
    if stage == "hmc" and TEACHER_MODEL not in list_pretrained():
        print(f"[main] {TEACHER_MODEL!r} does not ship: the demo runs stage 1 from scratch instead")
        stage = "teacher"
    if stage == "scratch":
        return SCRATCH_DEMO, ("a small EV-FlowNet (width 8) from random weights, distilled on the stored teacher "
                              "targets of the default's recipe")
    if stage == "hmc":
        return [*HMC_STAGE, "--init", TEACHER_MODEL], (f"the recipe's stage 2 (per-window L_HMC) from the shipped "
                                                       f"model {TEACHER_MODEL!r}")
    return RECIPE, "the recipe's stage 1 (teacher solved in every update) from scratch"


def main(argv=None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    cut = argv.index("--") if "--" in argv else len(argv)
    args = options_from_args(MainOptions, build_parser().parse_args(argv[:cut]))
    args.set_threads()  # step 1 and the demo run in this process
    extra = argv[cut + 1 :]
    out = Path(args.out)
    device = ["--device", args.device]
    print("[main] 0/3 preparing the synthetic data this job uses (simulated once, then read from the cache)", flush=True)
    prepare_data([*args.eval_data, TRAIN_SPLIT, args.demo_val_data] if args.demo_minutes > 0 else list(args.eval_data))

    windows = ["--max-windows", str(args.eval_windows)] if args.eval_windows else []
    rows = [] if args.no_cmax else ["--cmax"]
    for data in args.eval_data:
        name = Path(data).name
        per_seq = f"the first {args.eval_windows} windows of each sequence" if args.eval_windows else "every window"
        if DEFAULT_PRETRAINED in list_pretrained():
            info = pretrained_info(DEFAULT_PRETRAINED)
            print(f"\n[main] 1/3 evaluating the default model {DEFAULT_PRETRAINED!r} ({info.get('date')}) in its mode "
                  f"(the network's proposal finished by a short solve) and alone, zero flow"
                  f"{'' if args.no_cmax else ' and contrast maximisation (no network)'} on {data}, {per_seq}",
                  flush=True)
            rows_here = ["--pretrained", "--zero", *rows]
        else:
            print(f"\n[main] 1/3 no pretrained model ships in agents/weights/: zero flow on {data}", flush=True)
            rows_here = ["--zero", *rows]
        evaluate_command.main([*rows_here, "--data", data, *windows, "--out", str(out / "eval" / name),
                              "--overwrite", *device])  # the job owns its --out: a rerun replaces it

    if args.demo_minutes > 0:
        recipe, what = demo_recipe(args)
        print(f"\n[main] 2/3 training demo: {what}; {args.demo_steps} steps or {args.demo_minutes:g} min, "
              f"whichever ends first, validated on {args.demo_val_data} at the start and every {args.demo_val_every} "
              "steps", flush=True)
        val = ["--val-data", args.demo_val_data, "--val-windows", str(VAL_WINDOWS), "--val-start",
               "--val-every", str(args.demo_val_every)]
        train_command.main([*recipe, "--minutes", str(args.demo_minutes), "--steps", str(args.demo_steps), *val,
                           "--out", str(out / "demo"), "--overwrite", *device, *extra])
        demo_summary(out / "demo" / "metrics.jsonl")
        demo_verdict(out / "demo" / "metrics.jsonl", args.demo_val_data)
        picture = plot_demo(out / "demo" / "metrics.jsonl", out / "demo" / "learning.png", args.demo_val_data)
        if picture:
            print(f"[main] the demo's curves: {picture}")

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
