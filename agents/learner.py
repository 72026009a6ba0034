"""Truncated-BPTT training of a recurrent flow policy through EventFlow env rollouts.

One update, read top to bottom (:meth:`Learner.update`):

1. collect the rollout: for L windows (``unroll``, paper: 10) the policy sees the B envs'
   observations and predicts multi-scale flows (differentiable, state carried); the finest flow
   (detached) is the action that advances the envs; where an episode ended, that element's
   recurrent state is reset;
2. hand the rollout to the objective (agents/objectives.py: per-window L_HMC / L_AT,
   accumulated L_HMC, the contrast-maximisation teacher, or supervised), which returns the loss;
3. backpropagate it, clip the gradient norm, step the optimizer;
4. detach the recurrent state (the next update continues the same sequences).

The envs run with ``compute_reward=False``: the learner computes the env's loss itself, with
gradients, on the B windows of a step padded into one batch: ``losses.window_loss`` of the
windows in ``info["window"]``, the border rule included (``border_penalty`` x the window's
zero-flow loss x the share of events pushed out of the image, ramped over ``border_ramp``
pixels); so each window's loss is the env's -reward for the same flow (the EventFlowEnv
docstring says when), and the env need not compute it twice.

Mixed precision (``amp``): the network's forward runs under autocast (bfloat16 by default on a
CUDA device that supports it; float16 on CUDA with loss scaling), the losses in float32.

Distributed: when ``torch.distributed`` is initialised (``torchrun``), each rank rolls out its
own shard of sequences, gradients are averaged across ranks after each backward in bucketed
all-reduces (``agents/distributed.py`` says why not DistributedDataParallel), and every rank
takes the same number of optimizer steps whatever the length of its shard. A checkpoint holds
every rank's episodes (gathered to rank 0) and each rank continues its own on a resume, which
therefore needs the same number of processes (``Learner.load_state_dict``).
"""

from __future__ import annotations

import dataclasses
import json
import math
from dataclasses import dataclass
from typing import Any, Literal

import gymnasium
import numpy as np
import torch
import torch.distributed as dist
from gymnasium.vector import AutoresetMode

from envs.env import EventFlowEnv, check_event_keep
from losses import (
    CMAX_WEIGHTS,
    EventBatch,
    LossWeights,
    check_border_ramp,
    window_loss,
    zero_flow_loss,
)

from .checkpoint import rng_state, set_rng_state
from .distributed import average_gradients, gather_to_first
from .objectives import RolloutWindow, loss_options, make_objective, windows_from_info
from .options import (
    ModelWidth,
    SensorSizeOptions,
    Windows,
    check_choices,
    keep_fraction,
    non_negative_float,
    non_negative_int,
    one_or_list,
    option,
    positive_float,
    positive_int,
    to_argv,
    torch_device,
)
from .policy import RecurrentPolicy, autocast_dtype
from .registry import make_model, width_kwargs
from .teacher import TeacherTargets

__all__ = ["TrainConfig", "Learner", "make_vector_env", "PRESETS", "preset_config", "preset_options"]


def _key_values(items) -> dict:
    """``KEY=VALUE`` items (VALUE read as JSON where it parses) as a dict; a dict passes unchanged."""
    if isinstance(items, dict):
        return items
    out = {}
    for item in items or []:
        key, sep, value = item.partition("=")
        if not sep:
            raise ValueError(f"--model-kwarg expects key=value, got {item!r}")
        try:
            out[key] = json.loads(value)
        except json.JSONDecodeError:
            out[key] = value
    return out


@dataclass
class TrainConfig(ModelWidth, Windows, SensorSizeOptions):
    """Everything a training run depends on (saved in every checkpoint). Each field is one option
    of ``scripts/train.py`` (agents/options.py writes the command line from this class); the
    string under a field is its help. ``width``, the windows (``window``, ``window_size``) and
    ``sensor_size`` are option groups the commands share (agents.options)."""

    model: str = "ev-mgrflownet"
    """registry name (ev-mgrflownet, ev-flownet, convgru-ev-flownet, xlif-ev-flownet, unet-*) or pkg.module:factory"""
    model_kwargs: dict = option(flag="--model-kwarg", action="append", metavar="KEY=VALUE", convert=_key_values,
                                default_factory=dict)
    """extra model argument, e.g. use_st_convgru=false (repeatable)"""
    input: Literal["count_image", "voxel_grid", "count_time_image"] = "count_image"
    """the paper's count image (eq. 2), a voxel grid (--voxel-bins), or EV-FlowNet's counts and timestamps"""
    voxel_bins: int = option(5, type=positive_int)
    """time bins of the voxel-grid input"""
    data: Any = option("synthetic-train", nargs="+", convert=one_or_list)
    """synthetic split name, recording files or directories"""
    crop: tuple[int, ...] | None = option(None, type=non_negative_int)
    """H W (centred) or TOP LEFT H W"""
    random_crop: bool = False
    """place the --crop H W window at a random position in each episode (validation uses whole frames)"""
    flips: bool = True
    """Hagenaars' random h/v/polarity flips, once per sequence (--no-flips: off)"""
    event_keep: tuple[float, ...] | None = option(None, type=keep_fraction, metavar="P")
    """thin the training events: keep each with probability P, or (LOW HIGH) with one drawn per episode log-uniformly in the range; the motion and its targets are unchanged, so the event density stops telling the speed"""
    num_envs: int = option(4, type=positive_int)
    """B, sequences rolled out in parallel"""
    vector: Literal["sync", "async"] = "sync"
    """gymnasium vector env: in this process or in worker processes"""
    unroll: int = option(10, type=positive_int)
    """L, windows per truncated-BPTT update (paper: 10)"""
    steps: int = option(1000, type=non_negative_int)
    """total optimizer steps (0: save the starting weights, e.g. of --init, as a new run)"""
    lr: float = option(1e-4, type=non_negative_float)
    """Adam step size (paper)"""
    warmup_steps: int = option(0, type=non_negative_int)
    """steps of linear warm-up of the step size"""
    decay: Literal["none", "cosine"] = "none"
    """step-size decay over --steps"""
    grad_clip: float = option(100.0, type=positive_float)
    """gradient norm clip (Hagenaars)"""
    moment_warmup: int = option(50, type=non_negative_int)
    """steps of linear warm-up after a resume whose state holds no Adam moments (a campaign's slim state)"""
    loss: Literal["hmc", "at", "teacher", "supervised"] = "hmc"
    """hmc (paper), at (baseline), teacher (regress per-window contrast maximisation), supervised (a reference)"""
    loss_mode: Literal["window", "accumulated"] = "window"
    """window: the mean of the L windows' losses; accumulated: one loss over all L (Hagenaars' sequential learning)"""
    # The loss readings the paper leaves open (docs/method.md).
    loss_scales: Literal["all", "finest"] = "all"
    """all: every decoder scale's flow in the loss, averaged; finest: the full-resolution flow only"""
    upsampling: Literal["bilinear", "nearest"] = "bilinear"
    """how coarse scales' flows reach full resolution in the loss"""
    reference_times: Literal["window", "events"] = "window"
    """window: references at the window bounds; events: at the first and last event"""
    at_normalisation: Literal["event_pixels", "sum"] = "event_pixels"
    """L_AT over the pixels holding events, or sum: eq. 14's bare sum"""
    lambda_1: float = option(LossWeights.lambda_1, type=non_negative_float)
    """weight of the event-count term in L_HMC (eq. 17)"""
    lambda_2: float = option(LossWeights.lambda_2, type=non_negative_float)
    """weight of the smoothness term (eq. 17)"""
    alpha: float = option(LossWeights.alpha, type=positive_float)
    """Charbonnier exponent of the smoothness term (eq. 16)"""
    border_penalty: float = LossWeights.border_penalty
    """border rule weight: x zero-flow loss x share of events pushed out of the image (0: the paper's loss)"""
    border_ramp: float = LossWeights.border_ramp
    """border rule ramp: an event d px beyond the image pays min(1, d / ramp) of its share (0: all of it)"""
    flow_scaling: float | None = option(None, type=positive_float)
    """pixels per network unit (default max(H, W))"""
    teacher_grids: tuple[int, ...] = option((4, 8), type=positive_int)
    """teacher: coarse-to-fine grid cells along the longer side"""
    teacher_steps: int = option(40, type=positive_int)
    """teacher: Adam steps per level"""
    teacher_lr: float = option(0.05, type=positive_float)
    """teacher: Adam step size (pixels)"""
    teacher_lambda_2: float = option(CMAX_WEIGHTS.lambda_2, type=non_negative_float)
    """teacher: smoothness weight"""
    teacher_pixels: Literal["events", "all"] = "events"
    """teacher: regress on pixels holding events, or on every pixel"""
    teacher_max_events: int | None = option(None, type=positive_int)
    """teacher: solve on at most this many events per window, evenly subsampled (default: all)"""
    teacher_cache: str | None = None
    """teacher: precomputed targets (scripts/teacher_targets.py) instead of solving every update"""
    finish_steps: int = option(0, type=non_negative_int)
    """take the loss after K unrolled gradient steps of the window's L_HMC on the finest flow (losses/finish.py): the network trained as the proposal a short solve finishes (docs/finish.md); 0: none"""
    finish_lr: float = option(0.3, type=positive_float)
    """the unrolled finish's step: the mean move of a correction cell in pixels, times the window's length in 30 Hz frames"""
    finish_grid: int = option(16, type=positive_int)
    """the unrolled finish's correction grid: cells along the longer side"""
    head_init: float | None = option(None, metavar="A", type=non_negative_float)
    """re-draw the flow heads' weights from U(-A, A), biases 0 (start near zero flow)"""
    seed: int = option(0, type=non_negative_int)
    """seeds the initial weights, the episodes and the flips"""
    device: str = option("cpu", type=torch_device)
    """torch device"""
    amp: Literal["auto", "bf16", "fp16", "off"] = "auto"
    """mixed precision of the network's forward (losses stay float32): auto = bf16 on a CUDA device that supports it, else off; fp16: CUDA only"""

    def __post_init__(self) -> None:
        check_choices(self)
        if self.finish_steps and self.loss_mode == "accumulated" and self.loss in ("hmc", "at"):
            raise ValueError("--finish-steps finishes each window's flow: it needs --loss-mode window (or a teacher)")
        if self.event_keep is not None:  # refused where the options are read, not when the envs are built
            try:
                keep = check_event_keep(self.event_keep)
            except ValueError as err:
                raise ValueError(f"--event-keep: {err}") from None
            self.event_keep = None if keep is None else keep[:1] if keep[0] == keep[1] else keep

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    @property
    def weights(self) -> LossWeights:
        """The loss weights of this run."""
        return LossWeights(self.lambda_1, self.lambda_2, self.alpha, self.border_penalty, self.border_ramp)


_RECIPE = {"model": "ev-mgrflownet", "width": "cpu", "input": "voxel_grid", "crop": (64, 64), "random_crop": True,
           "flow_scaling": 32.0, "num_envs": 8, "unroll": 4}

#: Named recipes: TrainConfig values a preset sets (options given beside it still win).
PRESETS: dict[str, dict[str, Any]] = {
    # Zhuang et al. 2024, sec. IV-A: EV-MGRFlowNet at the paper's width on count images, all four
    # scales' flows in the loss, Adam at 1e-4, L = 10 windows per update, and L_HMC over those
    # windows as Hagenaars' sequential learning (one loss over the events of all L windows,
    # references 0 and L). The border rule stays on (docs/method.md says why; --border-penalty 0
    # gives the paper's bare loss).
    "paper": {
        "model": "ev-mgrflownet", "width": "paper", "input": "count_image", "lr": 1e-4, "unroll": 10,
        "loss": "hmc", "loss_mode": "accumulated", "loss_scales": "all", "lambda_1": LossWeights.lambda_1,
        "lambda_2": LossWeights.lambda_2, "alpha": LossWeights.alpha, "grad_clip": 100.0, "decay": "none",
        "warmup_steps": 0,
    },
    # The project's recipe (docs/results.md), stage 1: distil the per-window contrast-maximisation
    # teacher of L_HMC from targets solved once (scripts/teacher_targets.py); the shipped
    # ev-mgrflownet-cpu-synthetic was trained this way (its provenance gives the command).
    "teacher-cached": {**_RECIPE, "loss": "teacher", "teacher_cache": "runs/teacher-targets/train.h5",
                       "teacher_pixels": "all", "window_size": [1, 2, 3, 4], "lr": 1e-3, "head_init": 0.1},
    # stage 1 solving the teacher inside every update (no wait for the targets: the main job's demo)
    "teacher": {**_RECIPE, "loss": "teacher", "window_size": [1, 2, 3, 4], "lr": 1e-3, "head_init": 0.1,
                "teacher_steps": 20, "teacher_pixels": "all", "teacher_max_events": 8000},
    # stage 2: the paper's per-window L_HMC (the env's reward, ramped border rule) from stage 1
    # (ev-mgrflownet-cpu-synthetic-hmc's provenance)
    "hmc-stage": {**_RECIPE, "loss": "hmc", "window_size": 4, "lr": 3e-4},
}


def preset_config(name: str, **overrides) -> TrainConfig:
    """The TrainConfig of preset ``name`` with ``overrides`` on top."""
    if name not in PRESETS:
        raise ValueError(f"unknown preset {name!r}; presets: {sorted(PRESETS)}")
    return TrainConfig(**{**PRESETS[name], **overrides})


def preset_options(name: str) -> list[str]:
    """The scripts/train.py options that spell out preset ``name``."""
    return to_argv(TrainConfig, PRESETS[name])


def data_options(cfg: TrainConfig) -> dict:
    """The reader options of the run's recordings (``sensor_size``, for files without geometry)."""
    return cfg.data_options()


def make_vector_env(cfg: TrainConfig, *, rank: int = 0, world: int = 1, data=None, flips=None):
    """B EventFlow envs over this rank's shard of the recordings, autoresetting in the same
    step (the observation returned with ``truncated=True`` already opens the next sequence)."""
    data = cfg.data if data is None else data
    options = data_options(cfg)
    probe = EventFlowEnv(data, window=cfg.window, window_size=cfg.window_size, crop=cfg.crop,
                         random_crop=cfg.random_crop, data_options=options)
    n_seq = len(probe.sources)
    probe.close()
    shard = list(range(rank, n_seq, world)) if world > 1 and n_seq >= world else None
    kwargs = dict(
        data=data, window=cfg.window, window_size=cfg.window_size, crop=cfg.crop, random_crop=cfg.random_crop,
        flips=cfg.flips if flips is None else flips, event_keep=cfg.event_keep, compute_reward=False, sequences=shard,
        flow_scaling=cfg.flow_scaling, observations=(cfg.input,), voxel_bins=cfg.voxel_bins, data_options=options,
    )
    fns = [lambda i=i: EventFlowEnv(**kwargs, env_index=i) for i in range(cfg.num_envs)]
    cls = gymnasium.vector.SyncVectorEnv if cfg.vector == "sync" else gymnasium.vector.AsyncVectorEnv
    return cls(fns, autoreset_mode=AutoresetMode.SAME_STEP)


def init_flow_heads(model: torch.nn.Module, scale: float) -> None:
    """Start a built-in network near zero flow: its flow heads' weights ~ U(-scale, scale),
    biases 0, and (EV-MGRFlowNet) the FGD refiners' input biases 0, so that a zero estimate
    with a zero prior refines to zero instead of tanh(bias) x flow_scaling. Models without
    ``decoder.heads`` (e.g. plug-ins) raise a ValueError."""
    heads = getattr(getattr(model, "decoder", None), "heads", None)
    if heads is None:
        raise ValueError(f"head_init: model {type(model).__name__} has no decoder.heads to re-initialise")
    with torch.no_grad():
        for head in heads:
            head.weight.uniform_(-scale, scale)
            if head.bias is not None:
                head.bias.zero_()
        for refiner in getattr(model.decoder, "refiners", None) or []:
            refiner.x_convs.bias.zero_()


class Learner:
    """Owns the policy, optimizer and training envs of one process."""

    def __init__(self, cfg: TrainConfig) -> None:
        check_choices(cfg)  # again: a field may have been set after the config was made
        check_border_ramp(cfg.border_ramp)  # before any env or output exists
        if cfg.teacher_cache and cfg.loss != "teacher":
            raise ValueError(f"teacher_cache is for loss 'teacher', not {cfg.loss!r}")
        self.teacher = TeacherTargets(cfg.teacher_cache) if cfg.teacher_cache else None
        self.cfg = cfg
        self.device = torch.device(cfg.device)
        self.rank = dist.get_rank() if dist.is_initialized() else 0
        self.world = dist.get_world_size() if dist.is_initialized() else 1
        torch.manual_seed(cfg.seed)  # same initial weights on every rank
        np.random.seed(cfg.seed + self.rank)
        self.envs = make_vector_env(cfg, rank=self.rank, world=self.world)
        space = self.envs.single_action_space
        self.height, self.width = space.shape[1:]
        self.flow_scaling = float(cfg.flow_scaling or max(self.height, self.width))
        in_channels = {"count_image": 2, "count_time_image": 4}.get(cfg.input, cfg.voxel_bins)
        self.model_config = {**width_kwargs(cfg.width), "flow_scaling": self.flow_scaling, "in_channels": in_channels,
                             **cfg.model_kwargs}
        model = make_model(cfg.model, **self.model_config)
        if cfg.head_init is not None:
            init_flow_heads(model, cfg.head_init)
        self.model_config = dict(getattr(model, "config", self.model_config))
        self.autocast = autocast_dtype(cfg.amp, self.device)  # None: float32
        self.policy = RecurrentPolicy(model, device=self.device, input_key=cfg.input, voxel_bins=cfg.voxel_bins,
                                      autocast=self.autocast)
        # float16's narrow range: the loss is scaled up for the backward, the gradients unscaled before the clip
        self.scaler = torch.amp.GradScaler("cuda") if self.autocast == torch.float16 else None
        if self.world > 1:
            for p in self.policy.parameters():
                dist.broadcast(p.data, src=0)
        self.optimizer = torch.optim.Adam(self.policy.parameters(), lr=cfg.lr)
        self.rewarm_from: int | None = None  # the step Adam's moments restarted at (a campaign's slim state)
        self.scheduler = torch.optim.lr_scheduler.LambdaLR(self.optimizer, self._lr_factor)
        self.step = 0
        self.loss_options = loss_options(cfg, self.flow_scaling)
        self.objective = make_objective(cfg, self.flow_scaling, device=self.device, height=self.height,
                                        width=self.width, teacher=self.teacher)
        self.obs, self.info = self.envs.reset(seed=cfg.seed + 1000 * self.rank)
        self.policy.reset()

    def _lr_factor(self, step: int) -> float:
        cfg = self.cfg
        factor = 1.0
        if cfg.warmup_steps > 0:
            factor = min(1.0, (step + 1) / cfg.warmup_steps)
        if cfg.decay == "cosine":
            factor *= 0.5 * (1 + math.cos(math.pi * min(step, cfg.steps) / max(cfg.steps, 1)))
        if self.rewarm_from is not None and cfg.moment_warmup > 0:  # restarted moments: warm up again
            factor *= min(1.0, (step - self.rewarm_from + 1) / cfg.moment_warmup)
        return factor

    def update(self) -> dict[str, float]:
        """One truncated-BPTT update over ``unroll`` windows; returns logged scalars."""
        cfg = self.cfg
        rollout, logged_losses = [], []
        for _ in range(cfg.unroll):  # 1. collect the rollout
            x = torch.as_tensor(self.obs[cfg.input], device=self.device)
            flows = self.policy(x)  # multi-scale, finest last, pixels per window
            # the B envs' windows in one padded batch: each window's loss is the one it has alone
            batch = EventBatch.from_windows(windows_from_info(self.info, cfg.num_envs), device=self.device)
            # the reference the border rule scales with, and a logged baseline
            zero = zero_flow_loss(flows[-1], batch, cfg.weights, **self.loss_options)
            if cfg.loss_mode == "window" or cfg.loss == "teacher":  # the finest flow's loss: the env's -reward
                with torch.no_grad():
                    logged_losses.append(window_loss(flows[-1].detach(), batch, cfg.weights, zero_flow=zero.per_sample,
                                                     **self.loss_options).loss)
            rollout.append(RolloutWindow(flows, batch, zero, self.info))
            self.obs, _, terminated, truncated, self.info = self.envs.step(flows[-1].detach().cpu().numpy())
            done = np.logical_or(terminated, truncated)
            if done.any():
                self.policy.reset(mask=done)  # new sequences start from a fresh state
        loss, extra = self.objective(rollout)  # 2. the loss of the rollout
        self.optimizer.zero_grad(set_to_none=True)  # 3. backward, average across ranks, clip, step
        (loss if self.scaler is None else self.scaler.scale(loss)).backward()
        if self.world > 1:
            average_gradients(self.policy.parameters(), self.world)
        if self.scaler is not None:
            self.scaler.unscale_(self.optimizer)
        grad_norm = torch.nn.utils.clip_grad_norm_(self.policy.parameters(), cfg.grad_clip)
        lr = self.optimizer.param_groups[0]["lr"]  # this update's step size (the scheduler then sets the next)
        if self.scaler is None:
            self.optimizer.step()
        else:  # skips the step when a gradient overflowed, and adapts the scale
            self.scaler.step(self.optimizer)
            self.scaler.update()
        self.scheduler.step()
        self.policy.detach()  # 4. truncated BPTT: the next update continues, without the graph
        self.step += 1
        if logged_losses:
            extra["model_hmc"] = torch.stack(logged_losses).mean()
        return {
            **{k: float(v) for k, v in extra.items()},
            "step": self.step,
            "loss": float(loss.detach()),
            "zero_flow_loss": float(torch.stack([w.zero.loss for w in rollout]).mean()),
            "grad_norm": float(grad_norm),
            "lr": lr,
            "events": sum(int(w.batch.mask.sum()) for w in rollout),
            "windows": cfg.unroll * cfg.num_envs,
        }

    # -- checkpoints -------------------------------------------------------------------------
    def episode_state(self) -> dict[str, Any]:
        """This process's place in its episodes: its random generators, the recurrent state, every
        env's episode position and the observation and info the next update starts from."""
        state = self.policy.state
        return {
            "rng": rng_state(self.device),
            "policy_state": None if state is None else {k: v.detach().cpu() for k, v in state.items()},
            "env_states": list(self.envs.call("episode_state")),
            "obs": {k: np.array(v) for k, v in self.obs.items()},
            # the current windows are left to the envs, which reload them on a resume
            "info": {k: v for k, v in self.info.items() if k not in ("window", "_window")},
        }

    def state_dict(self) -> dict[str, Any]:
        """The training checkpoint: weights, optimizer, scheduler, step, config, and the episodes.

        Rank 0's episode state (:meth:`episode_state`) sits at the top level, as in a
        single-process checkpoint; under ``torch.distributed`` this is a collective (every rank
        calls it) that gathers the other ranks' to rank 0, into ``rank_episodes[r - 1]`` for rank
        r, and ``world_size`` records how many there were. Only rank 0's dict is complete."""
        episode = self.episode_state()
        others = gather_to_first(episode) if self.world > 1 else None
        return {
            "model_name": self.cfg.model,
            "model_config": self.model_config,
            "model": self.policy.model.state_dict(),
            "optimizer": self.optimizer.state_dict(),
            "scheduler": self.scheduler.state_dict(),
            "scaler": None if self.scaler is None else self.scaler.state_dict(),
            "step": self.step,
            "config": self.cfg.to_dict(),
            "rewarm_from": self.rewarm_from,
            **episode,
            "world_size": self.world,
            "rank_episodes": [] if others is None else others[1:],
        }

    def stored_episode(self, payload: dict[str, Any]) -> dict[str, Any] | None:
        """This rank's episode state in a checkpoint, or None when the checkpoint was written by
        another number of processes (rank r's episodes belong to rank r's shard of sequences)."""
        if int(payload.get("world_size", 1)) != self.world:
            return None
        return payload if self.rank == 0 else payload["rank_episodes"][self.rank - 1]

    def load_state_dict(self, payload: dict[str, Any], *, restore_episodes: bool = True) -> None:
        """Continue the run of a training checkpoint. The step size follows ``cfg.lr`` (the
        stored one unless a resume was allowed to change it). restore_episodes: False starts
        fresh episodes (when the data or the windows changed) instead of the stored ones.

        Each rank takes back its own episodes and random generators (:meth:`stored_episode`); a
        checkpoint of another number of processes raises ValueError unless restore_episodes is
        False (then the ranks start fresh episodes from their own seeds)."""
        episode = self.stored_episode(payload)
        if restore_episodes and episode is None:
            stored = int(payload.get("world_size", 1))
            raise ValueError(
                f"the checkpoint holds the episodes of {stored} process(es), this run has {self.world}: each process "
                f"continues its own shard's episodes, so resume with {stored} process(es), or start fresh episodes "
                "(restore_episodes=False; scripts/train.py: --allow-changes world_size)")
        self.policy.model.load_state_dict(payload["model"])
        self.optimizer.load_state_dict(payload["optimizer"])
        self.scheduler.load_state_dict(payload["scheduler"])
        self.step = int(payload["step"])
        self.rewarm_from = payload.get("rewarm_from")
        if not payload["optimizer"].get("state") and self.step > 0:
            # a slim state without Adam's moments (evflow_cli.campaign): they restart from zero, and
            # the step size warms up again over cfg.moment_warmup steps so the first steps stay small
            self.rewarm_from = self.step
        self.scheduler.base_lrs = [self.cfg.lr for _ in self.optimizer.param_groups]
        for group in self.optimizer.param_groups:
            group["initial_lr"] = self.cfg.lr
            group["lr"] = self.cfg.lr * self._lr_factor(self.scheduler.last_epoch)
        if self.scaler is not None and payload.get("scaler"):
            self.scaler.load_state_dict(payload["scaler"])
        if episode is not None:
            set_rng_state(episode["rng"], self.device)
        state = episode.get("policy_state") if restore_episodes else None
        self.policy.state = None if state is None else {k: v.to(self.device) for k, v in state.items()}
        if restore_episodes and episode.get("env_states") is not None:
            self.envs.call("restore_episode_state", episode["env_states"])
            self.obs, self.info = episode["obs"], dict(episode["info"])
            windows = self.envs.call("current_window")
            self.info["window"] = np.empty(len(windows), object)
            for i, window in enumerate(windows):  # one by one: numpy would read a Window as a sequence
                self.info["window"][i] = window
            self.info["_window"] = np.ones(len(windows), bool)

    def close(self) -> None:
        self.envs.close()
