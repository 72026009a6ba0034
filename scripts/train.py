#!/usr/bin/env python
"""Train a flow policy with truncated BPTT through EventFlow env rollouts.

Examples:
  python scripts/train.py --steps 500 --out runs/mgr                 # EV-MGRFlowNet, CPU width
  python scripts/train.py --model convgru-ev-flownet --loss at --out runs/baseline
  python scripts/train.py --model mypkg.models:build --out runs/mine  # any protocol module
  python scripts/train.py --resume runs/mgr/checkpoint.pt --steps 1000
  torchrun --nproc_per_node=2 scripts/train.py --steps 100 --out runs/ddp

Writes OUT/metrics.jsonl (one line per optimizer step, plus validation lines),
OUT/checkpoint.pt (every --ckpt-every steps, on Ctrl-C and at the end; atomic) and OUT/config.json.
"""

from __future__ import annotations

import argparse
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

from agents.checkpoint import load_checkpoint, save_checkpoint  # noqa: E402
from agents.evaluation import evaluate  # noqa: E402
from agents.learner import Learner, TrainConfig  # noqa: E402
from agents.policy import RecurrentPolicy  # noqa: E402
from agents import pretrained as shipped  # noqa: E402


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
    g = p.add_argument_group("model")
    g.add_argument("--model", default=d.model, help="registry name (ev-mgrflownet, ev-flownet, convgru-ev-flownet, xlif-ev-flownet) or package.module:factory")
    g.add_argument("--width", default=d.width, help="'paper' (base width 32), 'cpu' (8) or an integer base width")
    g.add_argument("--input", default=d.input, choices=["count_image", "voxel_grid"],
                   help="network input: the paper's 2-channel count image, or a voxel grid (--voxel-bins)")
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
    g.add_argument("--loss-mode", default=d.loss_mode, choices=["window", "accumulated"])
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
                   help="continue from CHECKPOINT (default with no value: OUT/checkpoint.pt); its config is used, --steps/--minutes/--out may change")
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
        loss_mode=args.loss_mode, lambda_1=args.lambda_1, lambda_2=args.lambda_2, alpha=args.alpha,
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


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    world = int(os.environ.get("WORLD_SIZE", "1"))
    if world > 1:
        backend = "nccl" if args.device.startswith("cuda") else "gloo"
        dist.init_process_group(backend)
        if args.device.startswith("cuda"):
            args.device = f"cuda:{int(os.environ.get('LOCAL_RANK', 0))}"
    rank = dist.get_rank() if dist.is_initialized() else 0
    out = Path(args.out)
    payload = None
    if args.resume:
        resume = out / "checkpoint.pt" if args.resume == "auto" else Path(args.resume)
        payload = load_checkpoint(resume)
        # checkpoints from before the border rule's ramp existed trained with the plain rule
        cfg = TrainConfig(**{"border_ramp": 0.0, **payload["config"]})
        cfg.steps, cfg.device = args.steps, args.device
    else:
        cfg = config_from_args(args)
    learner = Learner(cfg)
    if payload is not None:
        learner.load_state_dict(payload)
    elif args.init:
        init_weights(learner, Path(args.init))
    if rank == 0:
        out.mkdir(parents=True, exist_ok=True)
        (out / "config.json").write_text(json.dumps(cfg.to_dict(), indent=2, default=str))
    log = open(out / "metrics.jsonl", "a") if rank == 0 else None

    def save() -> None:
        if rank == 0:
            save_checkpoint(out / "checkpoint.pt", learner.state_dict())

    interrupted = {"flag": False}
    previous = signal.signal(signal.SIGINT, lambda *_: interrupted.__setitem__("flag", True))
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
            stop = interrupted["flag"] or (args.minutes is not None and elapsed > 60 * args.minutes)
            if dist.is_initialized():  # every rank stops on the same step
                flag = torch.tensor([float(stop)])
                dist.all_reduce(flag, op=dist.ReduceOp.MAX)
                stop = bool(flag.item())
            if stop:
                break
    finally:
        bar.close()
        save()
        signal.signal(signal.SIGINT, previous)
        if rank == 0:
            if interrupted["flag"]:
                print(f"interrupted at step {learner.step}; saved {out / 'checkpoint.pt'}", file=sys.stderr)
            if args.val_data and not interrupted["flag"]:
                val = {"step": learner.step, **validate(learner, args.val_data, args.val_windows)}
                log.write(json.dumps(val) + "\n")
                print(" ".join(f"{k}={v:.4f}" if isinstance(v, float) else f"{k}={v}" for k, v in val.items()))
            log.close()
        learner.close()
        if dist.is_initialized():
            if sys.exc_info()[0] is None:  # tear down together: a rank whose peer already left can abort in gloo
                dist.barrier()
            dist.destroy_process_group()
    return 0


if __name__ == "__main__":
    sys.exit(main())
