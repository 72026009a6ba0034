"""Train a flow policy with truncated BPTT through EventFlow env rollouts.

Examples:
  python scripts/train.py --steps 500 --out runs/mgr                 # EV-MGRFlowNet, CPU width
  python scripts/train.py --preset paper --out runs/paper            # the paper's recipe (docs/method.md)
  python scripts/train.py --preset paper --border-penalty 0 --width cpu --out runs/paper-bare
  python scripts/train.py --model convgru-ev-flownet --loss at --out runs/baseline
  python scripts/train.py --model mypkg.models:build --out runs/mine  # any protocol module
  python scripts/train.py --resume runs/mgr/checkpoint.pt --steps 1000
  python scripts/train.py --data old_camera.raw --sensor-size 480 640 --logger tensorboard --val-every 50
  python scripts/train.py --resume --out runs/mgr --lr 5e-5 --allow-changes lr
  torchrun --nproc_per_node=2 scripts/train.py --steps 100 --out runs/ddp

Writes OUT/metrics.jsonl (one line per optimizer step, plus validation lines),
OUT/checkpoint.pt (every --ckpt-every steps, on Ctrl-C / SIGINT, on SIGTERM and at the end;
atomic) and OUT/config.json; with --logger tensorboard also OUT/tensorboard/ (the same scalars,
and a flow panel at each validation: evflow_cli/tensorboard_log.py). A new run in an OUT that holds
an earlier run's checkpoint or metrics is refused: --resume continues it, --overwrite starts afresh.

--resume continues the stored run: its configuration is used, and an option given on this command
line that differs from it is refused, naming each field, unless --allow-changes lists it (run
options --steps, --minutes, --out, --device, --ckpt-every and --val-* may always change, --steps
too unless the step size decays with --decay cosine; the network's shape never: fine-tune with
--init). metrics.jsonl is cut back to the checkpoint's step, so every step is logged once.

--preset NAME sets the values of a named recipe (agents.train_config.PRESETS); options given beside
it override them: paper (docs/method.md), and the project's recipe: teacher-cached (stage 1 on
stored teacher targets), teacher (stage 1 solving them in every update), hmc-stage (stage 2).

Distributed (torchrun): each rank uses the GPU of its LOCAL_RANK with NCCL, or the CPU with gloo,
rolls out its own shard of the sequences and validates its share of the validation sequences;
the checkpoint holds every rank's episodes, and a resume continues each on the rank it came from,
so it needs the same number of processes (--allow-changes world_size: fresh episodes instead).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import signal
import sys
import time
from dataclasses import dataclass
from datetime import timedelta
from pathlib import Path
from typing import Literal, NoReturn

import torch
import torch.distributed as dist
from tqdm import tqdm

from agents import pretrained as shipped
from agents.checkpoint import check_model_name, load_checkpoint, save_checkpoint
from agents.distributed import all_reduce_sums
from agents.dormant import FiringRecord, revive_decoder
from agents.evaluation import evaluate, first_window_panel
from agents.learner import Learner, data_options
from agents.options import (
    Progress,
    add_options,
    expand_config,
    non_negative_float,
    non_negative_int,
    option,
    options_from_args,
    positive_int,
)
from agents.policy import RecurrentPolicy
from agents.provenance import code_version
from agents.train_config import PRESETS, TrainConfig
from envs.atomic import open_no_follow, remove_stale_temporaries, write_atomic
from envs.outputs import hold_folder, release_folder
from evflow_cli.tensorboard_log import TensorBoardLog, require_tensorboard


@dataclass
class RunOptions(Progress):
    """How long and where a run goes, not what it learns (free to change on --resume)."""

    config: str | None = option(None, metavar="FILE")
    """start from a run config file: a run's own OUT/config.json, or TOML/JSON of option = value (options given beside it win)"""
    preset: str | None = option(None, choices=sorted(PRESETS))
    """a named recipe's values (agents.train_config.PRESETS) under the options given beside it"""
    out: str = "runs/train"
    """output directory"""
    resume: str | None = option(None, nargs="?", const="auto", metavar="CHECKPOINT")
    """continue from CHECKPOINT (no value: OUT/checkpoint.pt) with its config; see --allow-changes"""
    allow_changes: str = option("", metavar="FIELDS")
    """with --resume: comma-separated config fields this command may change, e.g. lr,steps"""
    init: str | None = option(None, metavar="CHECKPOINT")
    """fine-tune from the weights of CHECKPOINT or of a shipped model (a fresh optimizer; the same network)"""
    revive: int = option(0, type=non_negative_int, metavar="WINDOWS")
    """with --init: first give the flow decoder's channels that fire on none of the first WINDOWS windows of each training sequence fresh incoming and zero outgoing weights (the flow on those windows is unchanged; agents.dormant)"""
    minutes: float | None = option(None, type=non_negative_float)
    """also stop (and save) after this many minutes (0: after the first step)"""
    ckpt_every: int = option(100, type=positive_int)
    """save the checkpoint every N steps"""
    val_every: int = option(0, type=non_negative_int)
    """validate every N steps (0: only at the end)"""
    val_start: bool = False
    """also validate the initial weights before the first update (the curve then starts where the training did)"""
    val_data: str = "synthetic-mini"
    """held-out data for validation ('' to skip)"""
    val_windows: int = option(20, type=positive_int)
    """windows per validation sequence"""
    logger: Literal["jsonl", "tensorboard"] = "jsonl"
    """jsonl: the curves in OUT/metrics.jsonl (always written; the docs' curves come from it); tensorboard: also in OUT/tensorboard/, the step and validation scalars and a flow panel at each validation (needs the 'tensorboard' extra)"""
    overwrite: bool = False
    """start a new run in an OUT that holds an earlier run's checkpoint or metrics (they are replaced)"""
    threads: int | None = option(None, type=positive_int)
    """torch CPU threads of this process (default: torch's choice; under torchrun, of each rank)"""


#: options that say how long and where a run goes, not what it learns: free to change on --resume
RUN_OPTIONS = frozenset(f.name for f in dataclasses.fields(RunOptions)) | {"device", "amp"}
GROUPS = {"model": "model", "data": "data", "num_envs": "optimisation", "loss": "loss", "seed": "run"}


def build_parser() -> argparse.ArgumentParser:
    """scripts/train.py's command line: a TrainConfig field per option, then the RunOptions."""
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_options(p, TrainConfig, groups=GROUPS, defaults={"device": "cuda" if torch.cuda.is_available() else "cpu"})
    add_options(p, RunOptions, groups={"preset": "run options"})
    return p


def config_from_args(args) -> TrainConfig:
    return options_from_args(TrainConfig, args)


def validate(learner: Learner, data: str, windows: int) -> dict:
    """Mean L_HMC and AEE of the current weights vs zero flow on held-out sequences.

    Under torch.distributed a collective: each rank scores its share of the sequences (sequence i
    on rank i mod world) and the sums are added across the ranks, so no rank waits idle for
    another's validation (a wait that could outlast the process group's timeout)."""
    policy = RecurrentPolicy(learner.policy.model, device=learner.device, input_key=learner.cfg.input,
                             voxel_bins=learner.cfg.voxel_bins)  # own state, float32
    val_crop = None if learner.cfg.random_crop else learner.cfg.crop  # random crops: whole frames
    options = dict(crop=val_crop, max_windows=windows, progress=False, flow_scaling=learner.flow_scaling,
                   shard=(learner.rank, learner.world), data_options=data_options(learner.cfg))
    # zero flow's L_HMC comes with the model's (the same windows); its own run takes its AEE only
    model, zero = evaluate(policy, data, measures=("loss",), **options), evaluate(None, data, measures=(), **options)
    keys = [("model", "hmc", model), ("model", "aee", model), ("zero", "hmc_zero", model), ("zero", "aee", zero)]
    sums = [value for _, key, rows in keys for value in (sum(r.sums[key] for r in rows), sum(r.counts[key] for r in rows))]
    if learner.world > 1:
        sums = all_reduce_sums(sums, learner.device)
    return {f"val_{key.removesuffix('_zero')}_{name}": sums[2 * i] / sums[2 * i + 1] if sums[2 * i + 1] else float("nan")
            for i, (name, key, _) in enumerate(keys)}


def log_validation(board: TensorBoardLog, learner: Learner, data: str, val: dict) -> None:
    """A validation's scalars in TensorBoard, and the panel of the first window with events of
    ``data`` (events, the current weights' flow with the colour wheel, ground truth where present;
    agents.evaluation.window_panel). Rank 0 only: no collective."""
    board.scalars(val, "val")
    policy = RecurrentPolicy(learner.policy.model, device=learner.device, input_key=learner.cfg.input,
                             voxel_bins=learner.cfg.voxel_bins)  # own state, float32
    picture = first_window_panel(policy, data, crop=None if learner.cfg.random_crop else learner.cfg.crop,
                                 flow_scaling=learner.flow_scaling, data_options=data_options(learner.cfg))
    if picture is not None:
        board.image("val/flow", picture, val["step"])
    board.flush()


#: model config keys that shape no weight: ``--init`` may change them (fine-tuning to a new setting)
WEIGHTLESS_MODEL_KEYS = frozenset({"input_norm"})


def _shaping(config) -> dict | None:
    return None if config is None else {k: v for k, v in config.items() if k not in WEIGHTLESS_MODEL_KEYS}


def init_weights(learner, path: Path) -> None:
    """Load the network weights of a training checkpoint, or of a shipped model given by name,
    into a new run (``--init``). The model and its config must agree, except settings that shape
    no weight (:data:`WEIGHTLESS_MODEL_KEYS`, e.g. ``--model-kwarg input_norm=nonzero-rms``)."""
    if not path.exists():
        if str(path) not in shipped.list_pretrained():
            raise FileNotFoundError(f"--init {path}: no such checkpoint, nor a shipped model "
                                    f"(shipped: {', '.join(shipped.list_pretrained()) or 'none'})")
        path = shipped.WEIGHTS_DIR / f"{path}.pt"
    payload = load_checkpoint(path)
    if _shaping(payload.get("model_config")) != _shaping(learner.model_config) or payload.get("model_name") != learner.cfg.model:
        raise ValueError(
            f"--init {path}: checkpoint holds {payload.get('model_name')} {payload.get('model_config')}, "
            f"this run builds {learner.cfg.model} {learner.model_config}"
        )
    learner.policy.model.load_state_dict(payload["model"])


def revive_dormant(learner: Learner, windows: int, echo=print) -> dict[str, int]:
    """``--revive``: roll the network through the first ``windows`` windows of every training
    sequence at each of the run's window lengths (whole frames or its fixed crop, its autocast), then
    re-initialise its decoder channels that fired on none of them
    (:func:`agents.dormant.revive_decoder`, seeded by the run's seed). Under torchrun each rank
    rolls its share of the sequences and the ranks agree on the channels that fired anywhere.
    Returns and echoes the channels revived per decoder stage."""
    cfg, model = learner.cfg, learner.policy.model
    stages = {f"decoder.upsamples.{level}": stage.conv.out_channels
              for level, stage in enumerate(getattr(getattr(model, "decoder", None), "upsamples", []))}
    policy = RecurrentPolicy(model, device=learner.device, input_key=cfg.input, voxel_bins=cfg.voxel_bins,
                             autocast=learner.autocast)
    record = FiringRecord(model)
    try:
        for size in cfg.window_sizes() or [None]:
            evaluate(policy, cfg.data, window=cfg.window, window_size=size, crop=None if cfg.random_crop else cfg.crop,
                     max_windows=windows, progress=False, flow_scaling=learner.flow_scaling,
                     data_options=data_options(cfg), shard=(learner.rank, learner.world))
    finally:
        record.close()
    # per stage: on how many ranks' windows each channel fired (a rank without sequences adds zeros)
    counts = [float(record.fired[name][c]) if name in record.fired else 0.0
              for name, size in stages.items() for c in range(size)] + [float(bool(record.fired))]
    if learner.world > 1:
        counts = all_reduce_sums(counts, learner.device)
    if not counts[-1]:
        raise ValueError(f"--revive: no window of {cfg.data} ran through the network")
    fired, at = {}, 0
    for name, size in stages.items():
        fired[name] = torch.tensor(counts[at:at + size]) > 0
        at += size
    revived = revive_decoder(model, fired, seed=cfg.seed)
    echo("[train] --revive: dormant decoder channels re-initialised: "
         + (", ".join(f"{name} {count}/{stages[name]}" for name, count in revived.items()) or "none"))
    return revived


#: fields that shape the network: a resume cannot change them (fine-tune with --init)
ARCHITECTURE = frozenset({"model", "width", "input", "voxel_bins", "model_kwargs", "flow_scaling", "head_init"})
#: fields that change the episodes: an allowed change starts fresh ones instead of the stored ones
EPISODE_FIELDS = frozenset({"data", "sensor_size", "window", "window_size", "crop", "random_crop", "flips", "event_keep", "num_envs", "vector", "seed"})


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


def stored_config(stored: dict) -> TrainConfig:
    """The TrainConfig a checkpoint's stored config trained with, older checkpoints included."""
    # checkpoints from before the border rule's ramp existed trained with the plain rule, and
    # those from before loss_scales with the finest flow only in the accumulated loss
    before = {"border_ramp": 0.0, "loss_scales": "finest" if stored.get("loss_mode") == "accumulated" else "all"}
    return TrainConfig(**{**before, **stored})


def resume_config(stored: dict, args, given: set[str], source: Path) -> tuple[TrainConfig, set[str]]:
    """The configuration a resume continues with, and the fields it changed.

    stored: the checkpoint's config. Each option given on the command line (``given``) must agree
    with it, except run options, ``steps`` (unless the step size decays over the steps) and the
    fields listed in ``--allow-changes``; otherwise ValueError names every differing field."""
    old = stored_config(stored)
    asked = config_from_args(args)
    allowed = {name.strip() for name in args.allow_changes.split(",") if name.strip()}
    fields = {f.name for f in dataclasses.fields(TrainConfig)}
    unknown = sorted(allowed - fields - {"world_size"})  # world_size: the number of processes (check_world_size)
    if unknown:
        raise ValueError(f"--allow-changes: unknown config field(s) {', '.join(unknown)}; fields: "
                         f"{', '.join(sorted(fields | {'world_size'}))}")
    fixed = sorted(allowed & ARCHITECTURE)
    if fixed:
        raise ValueError(f"--allow-changes {', '.join(fixed)}: a resume cannot change the network's shape; start a new run "
                         f"from these weights with --init {source}")
    changed = {}
    for dest in sorted(given - RUN_OPTIONS):
        name = dest
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
    cfg = dataclasses.replace(old, **{name: new for name, (_, new) in changed.items()}, device=args.device,
                              amp=args.amp if "amp" in given else old.amp)
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
    and drop a line cut by a kill; rewritten atomically (a symbolic link there is refused)."""
    if path.is_symlink():
        raise FileExistsError(f"{path}: is a symbolic link; refusing to read or write through it (remove the link)")
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
    write_atomic(path, "".join(line + "\n" for line in kept))


def check_new_run_folder(out: Path, overwrite: bool) -> None:
    """A new run (no --resume) in a folder holding an earlier run's checkpoint.pt or metrics.jsonl
    would replace the one and mix its steps into the other: FileExistsError naming them, unless
    ``overwrite`` (the new run then starts them afresh)."""
    used = [name for name in ("checkpoint.pt", "metrics.jsonl") if (out / name).is_file() and (out / name).stat().st_size]
    if used and not overwrite:
        raise FileExistsError(f"--out {out}: holds an earlier run ({', '.join(used)}); continue it with --resume, "
                              "start afresh with --overwrite, or give another --out")


#: how long a collective waits for the slowest rank before the job aborts (NCCL's own default is
#: 10 minutes): the ranks wait for rank 0's checkpoint write, and for the longest validation share
PROCESS_GROUP_TIMEOUT = timedelta(minutes=30)


def setup_distributed(args) -> int:
    """Under torchrun: bind this rank to the GPU of its LOCAL_RANK (NCCL) or to the CPU (gloo),
    and join the process group; returns the rank (0 without torchrun)."""
    if int(os.environ.get("WORLD_SIZE", "1")) <= 1:
        return 0
    if torch.device(args.device).type == "cuda":
        local_rank = int(os.environ.get("LOCAL_RANK", 0))
        torch.cuda.set_device(local_rank)
        args.device = f"cuda:{local_rank}"
        if torch.__version__.startswith("2.7.0"):  # its eager NCCL init (device_id) can hang: pytorch#153960
            os.environ.setdefault("TORCH_NCCL_USE_COMM_NONBLOCKING", "0")
        dist.init_process_group("nccl", device_id=torch.device(args.device), timeout=PROCESS_GROUP_TIMEOUT)
    else:
        dist.init_process_group("gloo", timeout=PROCESS_GROUP_TIMEOUT)
    return dist.get_rank()


def check_world_size(payload: dict, world: int, allow_changes: str, source: Path) -> bool:
    """Whether a resume continues the stored episodes: True when the checkpoint was written by as
    many processes as this run has (each continues the episodes of its own shard of sequences).
    Otherwise ValueError naming both counts, unless ``--allow-changes`` lists world_size: then
    False (every rank starts fresh episodes; weights, optimizer and step continue), said on stderr."""
    stored = int(payload.get("world_size", 1))
    if stored == world:
        return True
    if "world_size" not in {name.strip() for name in allow_changes.split(",")}:
        older = "" if "world_size" in payload else " (or by an older version, which kept rank 0's episodes only)"
        raise ValueError(
            f"--resume {source}: written by {stored} process(es){older}, this run has {world}; each process continues "
            f"the episodes of its own shard of sequences, so resume with {stored} (torchrun --nproc_per_node {stored}), "
            "or pass --allow-changes world_size to start fresh episodes on every process (weights, optimizer and step "
            "continue)")
    if not dist.is_initialized() or dist.get_rank() == 0:
        print(f"--resume {source}: written by {stored} process(es), this run has {world}: fresh episodes on every "
              "process (--allow-changes world_size)", file=sys.stderr)
    return False


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    """The command line, with the defaults of ``--preset`` (if given) under the options given."""
    parser = build_parser()
    argv = expand_config(parser, argv)
    known, _ = parser.parse_known_args(argv)
    if known.preset is not None:
        parser.set_defaults(**PRESETS[known.preset])
    args = parser.parse_args(argv)
    if args.revive and (not args.init or args.resume):
        parser.error("--revive re-initialises the dormant channels of the --init weights of a new run: give --init"
                     + (", not --resume (a resumed run keeps its weights)" if args.resume else ""))
    return args


def open_run(args, argv: list[str] | None, rank: int) -> tuple[TrainConfig, Learner, dict | None]:
    """The run's configuration and learner: a new run from the options (and --init), or the
    stored run of --resume with its episodes restored where the configuration and the number
    of processes allow; rank 0 prepares OUT (config.json, metrics cut back to the step)."""
    out = Path(args.out)
    world = dist.get_world_size() if dist.is_initialized() else 1
    payload, changed, same_world = None, set(), True
    if args.resume:
        source, payload = open_training_checkpoint(args.resume, out)
        given = given_options(argv)
        trusted = args.model if "model" in given else None  # a plug-in only when named on this command line
        for name in (payload.get("model_name"), (payload.get("config") or {}).get("model")):
            check_model_name(name, source, trusted=trusted)
        cfg, changed = resume_config(payload["config"], args, given, source)
        same_world = check_world_size(payload, world, args.allow_changes, source)
    else:
        cfg = config_from_args(args)
    learner = Learner(cfg)
    if payload is not None:  # each rank takes back its own episodes
        learner.load_state_dict(payload, restore_episodes=same_world and not changed & EPISODE_FIELDS)
    elif args.init:
        init_weights(learner, Path(args.init))
        if args.revive:
            revive_dormant(learner, args.revive, echo=print if rank == 0 else lambda *_: None)
    if rank == 0:
        hold_folder(out)  # one writer per run folder, for the run's life (torchrun: rank 0 writes it)
        if payload is None:  # checked again under the lock: a run that finished meanwhile is not replaced
            check_new_run_folder(out, args.overwrite)
        remove_stale_temporaries(out / "checkpoint.pt")  # left by a run killed while saving
        run = {"code": code_version(), "command": "scripts/train.py"}  # a note: --config skips keys starting with _
        write_atomic(out / "config.json", json.dumps({**cfg.to_dict(), "_run": run}, indent=2, default=str))
        if payload is not None:
            truncate_metrics(out / "metrics.jsonl", learner.step)
    return cfg, learner, payload


class RunRecord:
    """Where a run's numbers go on rank 0: OUT/metrics.jsonl (the record), TensorBoard with
    --logger tensorboard, and the progress bar; every other rank records nothing."""

    def __init__(self, args, learner: Learner, rank: int, resumed: bool) -> None:
        out = Path(args.out)
        self.args, self.learner = args, learner
        self.log = open_no_follow(out / "metrics.jsonl", "a" if resumed else "w") if rank == 0 else None
        self.board = (TensorBoardLog(out / "tensorboard", learner.step)
                      if rank == 0 and args.logger == "tensorboard" else None)
        self.bar = tqdm(total=learner.cfg.steps, initial=learner.step, unit="step",
                        disable=args.no_progress or rank != 0)

    def step(self, stats: dict) -> None:
        if self.log:
            self.log.write(json.dumps(stats) + "\n")
            self.log.flush()
        if self.board:
            self.board.scalars(stats, "train")
        shown = {"loss": f"{stats['loss']:.4f}", "zero": f"{stats['zero_flow_loss']:.4f}"}
        if "model_hmc" in stats:
            shown["hmc"] = f"{stats['model_hmc']:.4f}"
        self.bar.set_postfix(**shown, win_s=f"{stats['windows_per_s']:.1f}")
        self.bar.update(1)

    def validate(self, echo) -> None:
        """Scores the learner on --val-data (every rank takes part) and records the line."""
        args = self.args
        val = {"step": self.learner.step, **validate(self.learner, args.val_data, args.val_windows)}
        if self.log:
            self.log.write(json.dumps(val) + "\n")
            echo(" ".join(f"{k}={v:.4f}" if isinstance(v, float) else f"{k}={v}" for k, v in val.items()))
        if self.board:
            log_validation(self.board, self.learner, args.val_data, val)

    def close(self) -> None:
        self.bar.close()
        if self.log:
            self.log.close()
        if self.board:
            self.board.close()


def agreed_stop(interrupted: dict, args, elapsed: float, device: torch.device) -> list[bool]:
    """[a signal came, --minutes ran out], agreed by every rank under torchrun (each rank's
    flags on its own device, the maximum taken), so all stop on the same step."""
    stop = [interrupted["signal"] is not None, args.minutes is not None and elapsed > 60 * args.minutes]
    if dist.is_initialized():
        flags = torch.tensor(stop, dtype=torch.float32, device=device)
        dist.all_reduce(flags, op=dist.ReduceOp.MAX)
        stop = [bool(flag) for flag in flags.tolist()]
    return stop


_left_process_group = False  # set by tear_down once this process has left a torchrun process group


def tear_down(learner: Learner) -> None:
    """Closes the learner's envs and, under torchrun, leaves the process group together."""
    global _left_process_group
    learner.close()
    if dist.is_initialized():
        if sys.exc_info()[0] is None:  # tear down together: a rank whose peer already left can abort in gloo
            if learner.device.type == "cuda":
                dist.barrier(device_ids=[learner.device.index])
            else:
                dist.barrier()
        dist.destroy_process_group()
        _left_process_group = True


def exit_process(code: int) -> NoReturn:
    """End a training process with ``code`` (what ``scripts/train.py`` and ``evflow-train`` do
    with main's status). A torchrun rank that has left its process group ends at once, after
    flushing its output (``os._exit``), without the interpreter's finalisation: there, after a
    finished and saved run, gloo's C++ teardown aborted a rank now and then (SIGABRT,
    "terminate called without an active exception", no Python frame on the stack; 2 of 30
    two-rank CPU runs on a busy 2-core machine), and torchrun reported the whole job failed."""
    if not _left_process_group:
        sys.exit(code)
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):  # closed or gone: nothing left to lose
            pass
    os._exit(code)


def main(argv=None) -> int:
    args = parse_args(argv)
    try:
        return _main(args, argv)
    finally:
        release_folder(args.out)  # (a killed process's lock is released by the kernel)


def _prepare(args, out: Path) -> bool:
    """Before any work: the logger installed (else an error printed and False), a new run's
    folder free (``out``, unless resuming), torch's thread count as asked."""
    if args.logger == "tensorboard":
        try:
            require_tensorboard()
        except ImportError as err:
            print(f"error: {err}", file=sys.stderr)
            return False
    if not args.resume:
        check_new_run_folder(out, args.overwrite)
    if args.threads:
        torch.set_num_threads(args.threads)
    return True


def _main(args, argv) -> int:
    out = Path(args.out)
    if not _prepare(args, out):
        return 2
    rank = setup_distributed(args)
    cfg, learner, payload = open_run(args, argv, rank)
    record = RunRecord(args, learner, rank, resumed=payload is not None)

    def save() -> None:
        state = learner.state_dict()  # under torchrun a collective: every rank's episodes gathered to rank 0
        if rank == 0:
            save_checkpoint(out / "checkpoint.pt", state)

    # SIGINT (Ctrl-C) and SIGTERM (schedulers, timeout) both finish the step, save and stop
    interrupted = {"signal": None}
    handlers = {sig: signal.signal(sig, lambda signum, _: interrupted.__setitem__("signal", signum))
                for sig in (signal.SIGINT, signal.SIGTERM)}
    start, first_step = time.time(), learner.step
    signalled = False  # stopped by a signal on any rank (agreed by all)
    validated = None  # the step the last validation scored
    if args.val_start and args.val_data and learner.step < cfg.steps:
        record.validate(record.bar.write)
        validated = learner.step
    try:
        while learner.step < cfg.steps:
            stats = learner.update()
            elapsed = time.time() - start
            stats["windows_per_s"] = stats["windows"] * (learner.step - first_step) / max(elapsed, 1e-9)
            stats["elapsed_s"] = round(elapsed, 1)  # since this process started (resumes restart it)
            record.step(stats)
            if args.val_every and learner.step % args.val_every == 0 and args.val_data:
                record.validate(record.bar.write)
                validated = learner.step
            if learner.step % args.ckpt_every == 0:
                save()
            stop = agreed_stop(interrupted, args, elapsed, learner.device)
            signalled = stop[0]
            if any(stop):
                break
    finally:
        record.bar.close()
        failed = sys.exc_info()[0] is not None
        if not dist.is_initialized():  # one process: also a signal that came after the last step
            signalled = interrupted["signal"] is not None
        if not (failed and dist.is_initialized()):  # a collective with a failed peer would hang: the last save stands
            save()
        for sig, previous in handlers.items():
            signal.signal(sig, previous)
        if rank == 0 and interrupted["signal"] is not None:
            name = signal.Signals(interrupted["signal"]).name
            print(f"{name}: stopped at step {learner.step}; saved {out / 'checkpoint.pt'}", file=sys.stderr)
        if args.val_data and not signalled and not failed and validated != learner.step:
            record.validate(print)
        record.close()
        tear_down(learner)
    return 0

if __name__ == "__main__":
    exit_process(main())
