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
windows in ``info["window"]`` under the run's spec (``cfg.loss_spec``, the envs' too), the border
rule included (``border_penalty`` x the window's
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

import math
from typing import Any

import gymnasium
import numpy as np
import torch
import torch.distributed as dist
from gymnasium.vector import AutoresetMode

from envs.env import EventFlowEnv
from envs.representations import OBSERVATIONS
from losses import (
    EventBatch,
    window_loss,
    zero_flow_loss,
)

from .checkpoint import rng_state, set_rng_state
from .distributed import average_gradients, gather_to_first
from .objectives import RolloutWindow, loss_options, make_objective, windows_from_info
from .options import check_choices
from .policy import RecurrentPolicy, autocast_dtype
from .registry import make_model, width_kwargs
from .teacher import TeacherTargets
from .train_config import PRESETS, TrainConfig, preset_config, preset_options  # re-exported: their earlier address

__all__ = ["TrainConfig", "Learner", "make_vector_env", "PRESETS", "preset_config", "preset_options"]


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
        loss_spec=cfg.loss_spec,
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
        self.loss_spec = cfg.loss_spec  # its settings checked before any env or output exists
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
        in_channels = OBSERVATIONS[cfg.input].channels(cfg.voxel_bins)
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
            zero = zero_flow_loss(flows[-1], batch, self.loss_spec, **self.loss_options)
            if cfg.loss_mode == "window" or cfg.loss == "teacher":  # the finest flow's loss: the env's -reward
                with torch.no_grad():
                    logged_losses.append(window_loss(flows[-1].detach(), batch, self.loss_spec,
                                                     zero_flow=zero.per_sample, **self.loss_options).loss)
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
