#!/usr/bin/env python
"""Train a flow policy with truncated BPTT through EventFlow env rollouts.

Examples:
  python scripts/train.py --steps 500 --out runs/mgr                 # EV-MGRFlowNet, CPU width
  python scripts/train.py --preset paper --out runs/paper            # the paper's recipe (docs/method.md)
  python scripts/train.py --preset paper --border-penalty 0 --width cpu --out runs/paper-bare
  python scripts/train.py --model convgru-ev-flownet --loss at --out runs/baseline
  python scripts/train.py --model mypkg.models:build --out runs/mine  # any protocol module
  python scripts/train.py --resume runs/mgr/checkpoint.pt --steps 1000
  python scripts/train.py --resume --out runs/mgr --lr 5e-5 --allow-changes lr
  torchrun --nproc_per_node=2 scripts/train.py --steps 100 --out runs/ddp

Writes OUT/metrics.jsonl (one line per optimizer step, plus validation lines),
OUT/checkpoint.pt (every --ckpt-every steps, on Ctrl-C / SIGINT, on SIGTERM and at the end;
atomic) and OUT/config.json.

--resume continues the stored run: its configuration is used, and an option given on this command
line that differs from it is refused, naming each field, unless --allow-changes lists it (run
options --steps, --minutes, --out, --device, --ckpt-every and --val-* may always change, --steps
too unless the step size decays with --decay cosine; the network's shape never: fine-tune with
--init). metrics.jsonl is cut back to the checkpoint's step, so every step is logged once.

--preset NAME sets the defaults of a named recipe (agents.learner.PRESETS); options given beside
it override them. "paper": EV-MGRFlowNet at width 32 on count images, all scales in the loss,
Adam 1e-4, L = 10, L_HMC as sequential learning over the L windows, the border rule on.

Distributed (torchrun): each rank uses the GPU of its LOCAL_RANK with NCCL, or the CPU with gloo.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import signal
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import torch  # noqa: E402
import torch.distributed as dist  # noqa: E402
from tqdm import tqdm  # noqa: E402

from agents import pretrained as shipped  # noqa: E402
from agents.checkpoint import load_checkpoint, save_checkpoint  # noqa: E402
from agents.evaluation import evaluate  # noqa: E402
from agents.learner import PRESETS, Learner, TrainConfig  # noqa: E402
from agents.policy import RecurrentPolicy  # noqa: E402
from envs.atomic import remove_stale_temporaries, temporary_path  # noqa: E402


def parse_kv(items: list[str]) -> dict:
    out = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep:
            raise SystemExit(f"--model-kwarg expects key=value, got {item!r}")
        try:
            out[key] = json.loads(value)
        except json.JSONDecodeError:
            out[key] = value
    return out


def build_parser() -> argparse.ArgumentParser:
    d = TrainConfig()
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--preset", default=None, choices=sorted(PRESETS),
                   help="a named recipe's defaults (options given beside it win); paper: see docs/method.md")
    g = p.add_argument_group("model")
    g.add_argument("--model", default=d.model, help="registry name (ev-mgrflownet; the published baselines ev-flownet "
                   "(with --input count_time_image), convgru-ev-flownet, xlif-ev-flownet; unet-feedforward, unet-convgru, "
                   "unet-xlif-encoder) or package.module:factory")
    g.add_argument("--width", default=d.width, help="'paper' (base width 32), 'cpu' (8) or an integer base width")
    g.add_argument("--input", default=d.input, choices=["count_image", "voxel_grid", "count_time_image"],
                   help="network input: the paper's 2-channel count image, a voxel grid (--voxel-bins), or EV-FlowNet's "
                        "4-channel counts and latest timestamps")
    g.add_argument("--voxel-bins", type=int, default=d.voxel_bins)
    g.add_argument("--model-kwarg", action="append", default=[], metavar="KEY=VALUE", help="extra model argument, e.g. use_st_convgru=false (repeatable)")
    g = p.add_argument_group("data")
    g.add_argument("--data", nargs="+", default=[d.data], help="synthetic split name, recording files or directories")
    g.add_argument("--window", default=d.window, choices=["frames", "time", "count"])
    g.add_argument("--window-size", type=int, nargs="+", default=None,
                   help="frames: grid steps (1); time: us (10000); count: events (15000); "
                        "several values: one drawn per episode (e.g. 1 2 3 4)")
    g.add_argument("--crop", type=int, nargs="+", default=None, help="H W (centred) or TOP LEFT H W")
    g.add_argument("--random-crop", action="store_true",
                   help="place the --crop H W window at a random position in each episode (validation uses whole frames)")
    g.add_argument("--no-flips", action="store_true", help="disable the random h/v/polarity flips")
    g = p.add_argument_group("optimisation")
    g.add_argument("--num-envs", type=int, default=d.num_envs, help="B, sequences rolled out in parallel")
    g.add_argument("--vector", default=d.vector, choices=["sync", "async"])
    g.add_argument("--unroll", type=int, default=d.unroll, help="L, windows per truncated-BPTT update (paper: 10)")
    g.add_argument("--steps", type=int, default=d.steps, help="total optimizer steps")
    g.add_argument("--minutes", type=float, default=None, help="also stop (and save) after this many minutes")
    g.add_argument("--lr", type=float, default=d.lr)
    g.add_argument("--warmup-steps", type=int, default=d.warmup_steps)
    g.add_argument("--decay", default=d.decay, choices=["none", "cosine"])
    g.add_argument("--grad-clip", type=float, default=d.grad_clip)
    g = p.add_argument_group("loss")
    g.add_argument("--loss", default=d.loss, choices=["hmc", "at", "teacher", "supervised"],
                   help="hmc (paper), at (baseline), teacher (regress per-window contrast-maximisation flows of "
                        "L_HMC: unsupervised), supervised (endpoint error vs ground truth: a reference bound)")
    g.add_argument("--teacher-grids", type=int, nargs="+", default=list(d.teacher_grids),
                   help="teacher: coarse-to-fine grid cells along the longer side (default 4 8)")
    g.add_argument("--teacher-steps", type=int, default=d.teacher_steps, help="teacher: Adam steps per level")
    g.add_argument("--teacher-lr", type=float, default=d.teacher_lr, help="teacher: Adam step size (pixels)")
    g.add_argument("--teacher-lambda-2", type=float, default=d.teacher_lambda_2, help="teacher: smoothness weight")
    g.add_argument("--teacher-pixels", default=d.teacher_pixels, choices=["events", "all"],
                   help="teacher: regress on pixels holding events (default) or on every pixel")
    g.add_argument("--teacher-cache", default=d.teacher_cache,
                   help="teacher: precomputed targets (scripts/teacher_targets.py) instead of solving every update")
    g.add_argument("--teacher-max-events", type=int, default=d.teacher_max_events,
                   help="teacher: solve on at most this many events per window, evenly subsampled (default: all)")
    g.add_argument("--loss-mode", default=d.loss_mode, choices=["window", "accumulated"],
                   help="window: the mean of the L per-window losses; accumulated: one loss over the events of all L "
                        "windows (Hagenaars' sequential learning, window k's events at k + tau, references 0 and L)")
    g.add_argument("--loss-scales", default=d.loss_scales, choices=["all", "finest"],
                   help="all: every decoder scale's flow in the loss, averaged; finest: the full-resolution flow only")
    g.add_argument("--upsampling", default=d.upsampling, choices=["bilinear", "nearest"],
                   help="how coarse scales' flows reach full resolution in the loss")
    g.add_argument("--reference-times", default=d.reference_times, choices=["window", "events"],
                   help="window: references at the window bounds; events: at the first and last event")
    g.add_argument("--at-normalisation", default=d.at_normalisation, choices=["event_pixels", "sum"],
                   help="L_AT over the pixels holding events (default), or sum: eq. 14's bare sum")
    g.add_argument("--lambda-1", type=float, default=d.lambda_1)
    g.add_argument("--lambda-2", type=float, default=d.lambda_2)
    g.add_argument("--alpha", type=float, default=d.alpha)
    g.add_argument("--border-penalty", type=float, default=d.border_penalty,
                   help="border rule weight: x zero-flow loss x share of events pushed out of the image (0: the paper's loss)")
    g.add_argument("--border-ramp", type=float, default=d.border_ramp,
                   help="border rule ramp in pixels: an event landing d px beyond the image pays min(1, d / ramp) of "
                        "its share (0: the whole share however near; default %(default)s)")
    g.add_argument("--flow-scaling", type=float, default=None, help="pixels per network unit (default max(H, W))")
    g.add_argument("--head-init", type=float, default=None, metavar="A",
                   help="re-draw the flow heads' weights from U(-A, A), biases 0 (start near zero flow)")
    g = p.add_argument_group("run")
    g.add_argument("--out", default="runs/train", help="output directory")
    g.add_argument("--resume", nargs="?", const="auto", default=None, metavar="CHECKPOINT",
                   help="continue from CHECKPOINT (default with no value: OUT/checkpoint.pt); its config is used, an option "
                        "that differs from it is refused unless --allow-changes names it")
    g.add_argument("--allow-changes", default="", metavar="FIELDS",
                   help="with --resume: comma-separated config fields this command may change, e.g. lr,steps")
    g.add_argument("--init", default=None, metavar="CHECKPOINT",
                   help="start from the network weights of CHECKPOINT, a training checkpoint or the name of a shipped "
                        "model (fine-tuning: a fresh optimizer and this run's options; the model, width, input and "
                        "flow scaling must match)")
    g.add_argument("--seed", type=int, default=d.seed)
    g.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    g.add_argument("--ckpt-every", type=int, default=100)
    g.add_argument("--val-every", type=int, default=0, help="validate every N steps (0: only at the end)")
    g.add_argument("--val-data", default="synthetic-mini", help="held-out data for validation ('' to skip)")
    g.add_argument("--val-windows", type=int, default=20, help="windows per validation sequence")
    g.add_argument("--no-progress", action="store_true")
    return p


def config_from_args(args) -> TrainConfig:
    data = args.data[0] if len(args.data) == 1 else args.data
    width = int(args.width) if str(args.width).isdigit() else args.width
    return TrainConfig(
        model=args.model, width=width, model_kwargs=parse_kv(args.model_kwarg), input=args.input,
        voxel_bins=args.voxel_bins, data=data, window=args.window,
        window_size=(None if args.window_size is None else args.window_size[0] if len(args.window_size) == 1
                     else list(args.window_size)), crop=tuple(args.crop) if args.crop else None, flips=not args.no_flips,
        random_crop=args.random_crop,
        num_envs=args.num_envs, vector=args.vector, unroll=args.unroll, steps=args.steps, lr=args.lr,
        warmup_steps=args.warmup_steps, decay=args.decay, grad_clip=args.grad_clip, loss=args.loss,
        loss_mode=args.loss_mode, loss_scales=args.loss_scales, upsampling=args.upsampling,
        reference_times=args.reference_times, at_normalisation=args.at_normalisation, lambda_1=args.lambda_1, lambda_2=args.lambda_2, alpha=args.alpha,
        border_penalty=args.border_penalty, border_ramp=args.border_ramp, flow_scaling=args.flow_scaling, head_init=args.head_init,
        teacher_grids=tuple(args.teacher_grids), teacher_steps=args.teacher_steps, teacher_lr=args.teacher_lr,
        teacher_lambda_2=args.teacher_lambda_2, teacher_pixels=args.teacher_pixels,
        teacher_max_events=args.teacher_max_events, teacher_cache=args.teacher_cache, seed=args.seed, device=args.device,
    )


def validate(learner: Learner, data: str, windows: int) -> dict:
    """Mean L_HMC and AEE of the current weights vs zero flow on held-out sequences."""
    policy = RecurrentPolicy(learner.policy.model, device=learner.device, input_key=learner.cfg.input,
                             voxel_bins=learner.cfg.voxel_bins)  # own state
    val_crop = None if learner.cfg.random_crop else learner.cfg.crop  # random crops: whole frames
    named = {
        "model": evaluate(policy, data, crop=val_crop, max_windows=windows, progress=False, flow_scaling=learner.flow_scaling),
        "zero": evaluate(None, data, crop=val_crop, max_windows=windows, progress=False, flow_scaling=learner.flow_scaling),
    }
    out = {}
    for name, rows in named.items():
        for key in ("hmc", "aee"):
            total = sum(r.counts[key] for r in rows)
            out[f"val_{key}_{name}"] = sum(r.sums[key] for r in rows) / total if total else float("nan")
    return out


def init_weights(learner, path: Path) -> None:
    """Load the network weights of a training checkpoint, or of a shipped model given by name,
    into a new run (``--init``)."""
    if not path.exists():
        if str(path) not in shipped.list_pretrained():
            raise FileNotFoundError(f"--init {path}: no such checkpoint, nor a shipped model "
                                    f"(shipped: {', '.join(shipped.list_pretrained()) or 'none'})")
        path = shipped.WEIGHTS_DIR / f"{path}.pt"
    payload = load_checkpoint(path)
    if payload.get("model_config") != learner.model_config or payload.get("model_name") != learner.cfg.model:
        raise ValueError(
            f"--init {path}: checkpoint holds {payload.get('model_name')} {payload.get('model_config')}, "
            f"this run builds {learner.cfg.model} {learner.model_config}"
        )
    learner.policy.model.load_state_dict(payload["model"])


#: options that say how long and where a run goes, not what it learns: free to change on --resume
RUN_OPTIONS = frozenset({"out", "resume", "allow_changes", "init", "minutes", "device", "ckpt_every", "val_every",
                         "val_data", "val_windows", "no_progress"})
#: command-line dests whose TrainConfig field has another name
FIELD_OF = {"model_kwarg": "model_kwargs", "no_flips": "flips"}
#: fields that shape the network: a resume cannot change them (fine-tune with --init)
ARCHITECTURE = frozenset({"model", "width", "input", "voxel_bins", "model_kwargs", "flow_scaling", "head_init"})
#: fields that change the episodes: an allowed change starts fresh ones instead of the stored ones
EPISODE_FIELDS = frozenset({"data", "window", "window_size", "crop", "random_crop", "flips", "num_envs", "vector", "seed"})


def given_options(argv: list[str] | None) -> set[str]:
    """The dests of the options written on the command line (not left at their defaults)."""
    parser = build_parser()
    parser.set_defaults(**{action.dest: None for action in parser._actions})  # no option parses to None
    given = {dest for dest, value in vars(parser.parse_args(argv)).items() if value is not None}
    preset = vars(parser.parse_args(argv)).get("preset")
    if preset is not None:  # a preset asks for its values as if they were written out
        given |= set(PRESETS[preset])
    return given


def _comparable(value):
    return json.loads(json.dumps(value, default=str))  # tuples and lists alike


def resume_config(stored: dict, args, given: set[str], source: Path) -> tuple[TrainConfig, set[str]]:
    """The configuration a resume continues with, and the fields it changed.

    stored: the checkpoint's config. Each option given on the command line (``given``) must agree
    with it, except run options, ``steps`` (unless the step size decays over the steps) and the
    fields listed in ``--allow-changes``; otherwise ValueError names every differing field."""
    # checkpoints from before the border rule's ramp existed trained with the plain rule, and
    # those from before loss_scales with the finest flow only in the accumulated loss
    before = {"border_ramp": 0.0, "loss_scales": "finest" if stored.get("loss_mode") == "accumulated" else "all"}
    old = TrainConfig(**{**before, **stored})
    asked = config_from_args(args)
    allowed = {name.strip() for name in args.allow_changes.split(",") if name.strip()}
    fields = {f.name for f in dataclasses.fields(TrainConfig)}
    unknown = sorted(allowed - fields)
    if unknown:
        raise ValueError(f"--allow-changes: unknown config field(s) {', '.join(unknown)}; fields: {', '.join(sorted(fields))}")
    fixed = sorted(allowed & ARCHITECTURE)
    if fixed:
        raise ValueError(f"--allow-changes {', '.join(fixed)}: a resume cannot change the network's shape; start a new run "
                         f"from these weights with --init {source}")
    changed = {}
    for dest in sorted(given - RUN_OPTIONS):
        name = FIELD_OF.get(dest, dest)
        if name in fields and _comparable(getattr(asked, name)) != _comparable(getattr(old, name)):
            changed[name] = (getattr(old, name), getattr(asked, name))
    free = {"steps"} if old.decay == "none" else set()
    refused = [name for name in changed if name not in allowed | free]
    if refused:
        lines = "; ".join(f"{name}: stored {changed[name][0]!r}, asked {changed[name][1]!r}" for name in refused)
        raise ValueError(
            f"--resume {source}: this command changes the run's configuration ({lines}); pass "
            f"--allow-changes {','.join(refused)} to continue with the new values, or drop the option(s)"
        )
    cfg = dataclasses.replace(old, **{name: new for name, (_, new) in changed.items()}, device=args.device)
    return cfg, set(changed)


def open_training_checkpoint(resume: str, out: Path) -> tuple[Path, dict]:
    """(path, payload) of the checkpoint ``--resume`` names; a shipped model's name or a
    weights-only file raises ValueError pointing at --init."""
    path = out / "checkpoint.pt" if resume == "auto" else Path(resume)
    if not path.exists() and resume in shipped.list_pretrained():
        raise ValueError(f"--resume {resume}: is a shipped model (weights only), not a training run to continue; "
                         f"fine-tune from it with --init {resume}")
    payload = load_checkpoint(path)
    missing = [key for key in ("optimizer", "scheduler", "step", "config", "rng") if key not in payload]
    if missing:
        raise ValueError(f"--resume {path}: a weights-only model file (no {', '.join(missing)}), e.g. one written by "
                         f"export_model.py, not a training checkpoint; fine-tune from its weights with --init {path}")
    return path, payload


def truncate_metrics(path: Path, step: int) -> None:
    """Keep the lines of metrics.jsonl up to ``step`` (a resumed run logs the later ones again)
    and drop a line cut by a kill; rewritten atomically."""
    if not path.exists():
        return
    kept = []
    for line in path.read_text().splitlines():
        try:
            row = json.loads(line)
        except json.JSONDecodeError:
            continue
        if isinstance(row, dict) and row.get("step", 0) <= step:
            kept.append(line)
    remove_stale_temporaries(path)
    tmp = temporary_path(path)
    tmp.write_text("".join(line + "\n" for line in kept))
    os.replace(tmp, path)


def setup_distributed(args) -> int:
    """Under torchrun: bind this rank to the GPU of its LOCAL_RANK (NCCL) or to the CPU (gloo),
    and join the process group; returns the rank (0 without torchrun)."""
    if int(os.environ.get("WORLD_SIZE", "1")) <= 1:
        return 0
    if torch.device(args.device).type == "cuda":
        local_rank = int(os.environ.get("LOCAL_RANK", 0))
        torch.cuda.set_device(local_rank)
        args.device = f"cuda:{local_rank}"
        dist.init_process_group("nccl", device_id=torch.device(args.device))
    else:
        dist.init_process_group("gloo")
    return dist.get_rank()


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    """The command line, with the defaults of ``--preset`` (if given) under the options given."""
    parser = build_parser()
    known, _ = parser.parse_known_args(argv)
    if known.preset is not None:
        parser.set_defaults(**PRESETS[known.preset])
    return parser.parse_args(argv)


def main(argv=None) -> int:
    args = parse_args(argv)
    rank = setup_distributed(args)
    out = Path(args.out)
    payload, changed = None, set()
    if args.resume:
        source, payload = open_training_checkpoint(args.resume, out)
        cfg, changed = resume_config(payload["config"], args, given_options(argv), source)
    else:
        cfg = config_from_args(args)
    learner = Learner(cfg)
    if payload is not None:
        learner.load_state_dict(payload, restore_episodes=not changed & EPISODE_FIELDS)
    elif args.init:
        init_weights(learner, Path(args.init))
    if rank == 0:
        out.mkdir(parents=True, exist_ok=True)
        remove_stale_temporaries(out / "checkpoint.pt")  # left by a run killed while saving
        (out / "config.json").write_text(json.dumps(cfg.to_dict(), indent=2, default=str))
        if payload is not None:
            truncate_metrics(out / "metrics.jsonl", learner.step)
    log = open(out / "metrics.jsonl", "a") if rank == 0 else None

    def save() -> None:
        if rank == 0:
            save_checkpoint(out / "checkpoint.pt", learner.state_dict())

    # SIGINT (Ctrl-C) and SIGTERM (schedulers, timeout) both finish the step, save and stop
    interrupted = {"signal": None}
    handlers = {sig: signal.signal(sig, lambda signum, _: interrupted.__setitem__("signal", signum))
                for sig in (signal.SIGINT, signal.SIGTERM)}
    start = time.time()
    bar = tqdm(total=cfg.steps, initial=learner.step, unit="step", disable=args.no_progress or rank != 0)
    try:
        while learner.step < cfg.steps:
            stats = learner.update()
            elapsed = time.time() - start
            stats["windows_per_s"] = stats["windows"] * (learner.step - (payload or {}).get("step", 0)) / max(elapsed, 1e-9)
            stats["elapsed_s"] = round(elapsed, 1)  # since this process started (resumes restart it)
            if log:
                log.write(json.dumps(stats) + "\n")
                log.flush()
            shown = {"loss": f"{stats['loss']:.4f}", "zero": f"{stats['zero_flow_loss']:.4f}"}
            if "model_hmc" in stats:
                shown["hmc"] = f"{stats['model_hmc']:.4f}"
            bar.set_postfix(**shown, win_s=f"{stats['windows_per_s']:.1f}")
            bar.update(1)
            if args.val_every and learner.step % args.val_every == 0 and args.val_data and rank == 0:
                val = {"step": learner.step, **validate(learner, args.val_data, args.val_windows)}
                log.write(json.dumps(val) + "\n")
                bar.write(" ".join(f"{k}={v:.4f}" if isinstance(v, float) else f"{k}={v}" for k, v in val.items()))
            if learner.step % args.ckpt_every == 0:
                save()
            stop = interrupted["signal"] is not None or (args.minutes is not None and elapsed > 60 * args.minutes)
            if dist.is_initialized():  # every rank stops on the same step (the flag on the rank's own device)
                flag = torch.tensor([float(stop)], device=learner.device)
                dist.all_reduce(flag, op=dist.ReduceOp.MAX)
                stop = bool(flag.item())
            if stop:
                break
    finally:
        bar.close()
        save()
        for sig, previous in handlers.items():
            signal.signal(sig, previous)
        if rank == 0:
            if interrupted["signal"] is not None:
                name = signal.Signals(interrupted["signal"]).name
                print(f"{name}: stopped at step {learner.step}; saved {out / 'checkpoint.pt'}", file=sys.stderr)
            if args.val_data and interrupted["signal"] is None:
                val = {"step": learner.step, **validate(learner, args.val_data, args.val_windows)}
                log.write(json.dumps(val) + "\n")
                print(" ".join(f"{k}={v:.4f}" if isinstance(v, float) else f"{k}={v}" for k, v in val.items()))
            log.close()
        learner.close()
        if dist.is_initialized():
            if sys.exc_info()[0] is None:  # tear down together: a rank whose peer already left can abort in gloo
                if learner.device.type == "cuda":
                    dist.barrier(device_ids=[learner.device.index])
                else:
                    dist.barrier()
            dist.destroy_process_group()
    return 0


if __name__ == "__main__":
    sys.exit(main())
