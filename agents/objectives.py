"""What a training update minimises, given the rollout it collected (:meth:`Learner.update`).

One class per objective, each with one job: turn the L windows of a rollout into a scalar loss
(and a few logged scalars). ``make_objective`` picks one from ``TrainConfig.loss`` and
``loss_mode``; the choices themselves are checked where the config is made.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import torch

from envs.windows import Window
from losses import (
    EventBatch,
    LossOutput,
    LossSpec,
    accumulated_window_loss,
    contrast_maximisation_flow,
    event_pixel_mask,
    to_full_resolution,
    unrolled_finish,
    window_loss,
)

from .cmax import FRAME_US
from .train_config import TrainConfig

if TYPE_CHECKING:
    from .teacher import TeacherTargets

__all__ = ["RolloutWindow", "WindowLoss", "AccumulatedLoss", "TeacherLoss", "SupervisedLoss", "make_objective",
           "loss_options", "windows_from_info"]


@dataclass
class RolloutWindow:
    """One window of a rollout, for the B envs at once.

    flows: the network's multi-scale flows, finest last, (B, 2, h, w) pixels over the window, with
    their graph; batch: the B windows' events, padded into one batch; zero: their loss under zero
    flow (``losses.zero_flow_loss``, no graph: the reference the border rule scales with); info:
    the vector env's info of the window."""

    flows: list[torch.Tensor]
    batch: EventBatch
    zero: LossOutput
    info: dict


def loss_options(cfg: TrainConfig, flow_scaling: float) -> dict:
    """How ``losses.window_loss`` (and ``zero_flow_loss``) scores a window under ``cfg``, beside
    its spec ``cfg.loss_spec`` (L_HMC, eq. 17, or L_AT with ``loss="at"``; the teacher and
    supervised objectives log L_HMC): the flow's scaling and the readings docs/method.md lists.
    With the defaults this is the env's reward."""
    return {"flow_scaling": flow_scaling, "upsampling": cfg.upsampling, "reference_times": cfg.reference_times,
            "at_normalisation": cfg.at_normalisation}


def _hmc_spec(cfg: TrainConfig) -> LossSpec:
    """The run's spec with L_HMC, whatever loss it trains: the unrolled finish solves L_HMC
    (docs/finish.md), and the accumulated loss exists for L_HMC alone (``--loss at`` with
    ``--loss-mode accumulated`` is refused by TrainConfig)."""
    return dataclasses.replace(cfg.loss_spec, loss="hmc")


def _endpoint_error(flow: torch.Tensor, target: torch.Tensor, weight: torch.Tensor) -> torch.Tensor:
    """Mean endpoint error of (B, 2, H, W) ``flow`` against ``target``, weighted by (B, 1, H, W) ``weight``.

    The length is the square root of the summed squares rather than ``Tensor.norm(dim=1)``: the
    same values, but torch's norm over the 2 channels of an NCHW tensor is ~40x slower on CPU
    (about a tenth of a teacher update, docs/training.md). The clamp keeps the gradient at 0
    where flow == target, as the norm's is, instead of 0 x inf."""
    squared = (flow - target).square().sum(dim=1, keepdim=True)
    length = squared.clamp_min(torch.finfo(squared.dtype).tiny).sqrt()
    return (length * weight).sum() / weight.sum().clamp_min(1)


def _scales(cfg: TrainConfig, flows: list) -> list:
    """The scales that enter the loss: all four (averaged) or the finest only."""
    return flows if cfg.loss_scales == "all" else flows[-1:]


def _finished(cfg: TrainConfig, window: RolloutWindow, flow_scaling: float) -> list[torch.Tensor]:
    """The window's flows with the finest replaced by its unrolled finish (``cfg.finish_steps``
    gradient steps of the window's L_HMC, graph kept: losses/finish.py), so that the loss is taken
    after the finish; unchanged without one. The step is ``finish_lr`` times each window's length
    in 30 Hz frames."""
    if not cfg.finish_steps:
        return window.flows
    full = window.flows[-1]  # the finest scale: full sensor resolution (losses.to_full_resolution)
    windows = windows_from_info(window.info, full.shape[0])
    frames = torch.tensor([max(1.0, w.duration_us / FRAME_US) for w in windows],
                          dtype=full.dtype, device=full.device)
    finished = unrolled_finish(full, window.batch, steps=cfg.finish_steps, lr=cfg.finish_lr * frames,
                               grid=cfg.finish_grid, weights=_hmc_spec(cfg), flow_scaling=flow_scaling)
    return [*window.flows[:-1], finished]


class WindowLoss:
    """The mean over the L windows of each window's L_HMC / L_AT, with the border rule: the env's
    -reward (``losses.window_loss``), for the B windows of a step at once."""

    def __init__(self, cfg: TrainConfig, flow_scaling: float, **_) -> None:
        self.cfg, self.options, self.flow_scaling = cfg, loss_options(cfg, flow_scaling), flow_scaling
        self.spec = cfg.loss_spec

    def __call__(self, rollout: list[RolloutWindow]) -> tuple[torch.Tensor, dict]:
        losses = [window_loss(_scales(self.cfg, _finished(self.cfg, w, self.flow_scaling)), w.batch, self.spec,
                              zero_flow=w.zero.per_sample, **self.options).loss for w in rollout]
        return torch.stack(losses).mean(), {}


class AccumulatedLoss:
    """Hagenaars' sequential learning: one L_HMC over the events of all L windows (window k's
    events at k + tau, references 0 and L), ``losses.accumulated_window_loss``; with the border
    rule on, also the slope back into the frame (outside distance, same per-window weight) so that
    a net whose events all left the frame is not stuck where the dropped share is flat."""

    def __init__(self, cfg: TrainConfig, flow_scaling: float, **_) -> None:
        self.cfg, self.options, self.spec = cfg, loss_options(cfg, flow_scaling), _hmc_spec(cfg)

    def __call__(self, rollout: list[RolloutWindow]) -> tuple[torch.Tensor, dict]:
        flows = [_scales(self.cfg, w.flows) for w in rollout]
        return accumulated_window_loss(flows, [w.batch for w in rollout], self.spec, **self.options).loss, {}


class SupervisedLoss:
    """Mean endpoint error against the envs' ground truth over valid pixels, all scales (not the
    method: a reference for what the network can learn in a given budget)."""

    def __init__(self, cfg: TrainConfig, flow_scaling: float, *, device: torch.device, **_) -> None:
        self.device = device

    def _window(self, window: RolloutWindow) -> torch.Tensor:
        if "flow_gt" not in window.info:
            raise ValueError("loss 'supervised' needs data with ground-truth flow (e.g. a synthetic split)")
        gt = torch.as_tensor(np.asarray(window.info["flow_gt"]), device=self.device)
        valid = torch.as_tensor(np.asarray(window.info["flow_gt_valid"]), device=self.device).unsqueeze(1)
        return torch.stack([_endpoint_error(f, gt, valid) for f in to_full_resolution(window.flows)]).mean()

    def __call__(self, rollout: list[RolloutWindow]) -> tuple[torch.Tensor, dict]:
        return torch.stack([self._window(w) for w in rollout]).mean(), {}


def windows_from_info(info: dict, num_envs: int) -> list[Window]:
    """The B envs' current windows out of a vector env's stacked info."""
    return [info["window"][i] for i in range(num_envs)]


class TeacherLoss:
    """Mean endpoint error, on pixels holding events (or all pixels), between every scale of the
    network's flows and the per-window contrast-maximisation flow of L_HMC: all L x B windows of
    the rollout solved together, or read from precomputed targets (``teacher``); the teacher sees
    only the events. Logs ``zero_flow_teacher``, zero flow's distance to the targets."""

    def __init__(self, cfg: TrainConfig, flow_scaling: float, *, device: torch.device, height: int, width: int,
                 teacher: TeacherTargets | None = None) -> None:
        self.cfg, self.flow_scaling, self.device = cfg, flow_scaling, device
        self.height, self.width, self.teacher = height, width, teacher
        self.spec = dataclasses.replace(cfg.loss_spec, lambda_2=cfg.teacher_lambda_2)  # the solve's loss

    def _targets(self, windows: list[Window]) -> torch.Tensor:
        cfg = self.cfg
        if cfg.teacher_max_events:  # an even subsample along each window's stream
            windows = [w.subsample(cfg.teacher_max_events) for w in windows]
        return contrast_maximisation_flow(
            EventBatch.from_windows(windows, device=self.device), self.height, self.width, grids=cfg.teacher_grids,
            steps=cfg.teacher_steps, lr=cfg.teacher_lr, flow_scaling=self.flow_scaling,
            weights=self.spec,
        )

    def __call__(self, rollout: list[RolloutWindow]) -> tuple[torch.Tensor, dict]:
        cfg, n = self.cfg, self.cfg.num_envs
        windows = [window for w in rollout for window in windows_from_info(w.info, n)]
        if self.teacher is not None:
            target = torch.cat([self.teacher.targets_from_info(w.info, n) for w in rollout]).to(self.device)
        else:
            target = self._targets(windows)
        if cfg.teacher_pixels == "all":  # the coarse-grid flow, interpolated between cells with events
            weight = torch.ones_like(target[:, :1])
        else:
            batch = EventBatch.from_windows(windows, device=self.device)
            weight = event_pixel_mask(batch.x, batch.y, batch.mask, self.height, self.width).unsqueeze(1)
            weight = weight.to(target.dtype)
        errors, zero_errors = [], []
        for k, window in enumerate(rollout):
            t, w = target[k * n : (k + 1) * n], weight[k * n : (k + 1) * n]
            zero_errors.append(_endpoint_error(torch.zeros_like(t), t, w))
            errors += [_endpoint_error(f, t, w) for f in to_full_resolution(_finished(cfg, window, self.flow_scaling))]
        return torch.stack(errors).mean(), {"zero_flow_teacher": torch.stack(zero_errors).mean().detach()}


def make_objective(cfg: TrainConfig, flow_scaling: float, **context):
    """The objective of ``cfg``: the loss's class (and, for L_HMC / L_AT, its loss_mode's)."""
    if cfg.loss == "teacher":
        return TeacherLoss(cfg, flow_scaling, **context)
    if cfg.loss == "supervised":
        return SupervisedLoss(cfg, flow_scaling, **context)
    if cfg.loss_mode == "accumulated":
        return AccumulatedLoss(cfg, flow_scaling, **context)
    return WindowLoss(cfg, flow_scaling, **context)
