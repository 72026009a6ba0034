"""The loss of a window as the env's reward scores it: L_HMC (or L_AT) plus the border rule.

One function for every consumer (docs/method.md, "Losses"): the env's reward is
``-window_loss(action, window, spec)``; the learner calls it on a batch of windows with
gradients; the evaluation's L_HMC column and the contrast-maximisation solver (the teacher) call
it too. Everything the loss is lies in one :class:`LossSpec` (the loss, its weights and the
border rule: ``border_penalty`` x the window's loss under zero flow x the (ramped) share of its
events the flow pushes out of the image). :func:`accumulated_window_loss` is the same spec's
loss over the events of K windows at once (sequential learning).
"""

from __future__ import annotations

from typing import Literal, Protocol, Sequence

import torch

from .events import EventBatch
from .hmc import (
    AtNormalisation,
    FlowInput,
    LossOutput,
    ReferenceTimes,
    Upsampling,
    _accumulated,
    _per_window,
)
from .spec import LOSS_NAMES, LossSpec, border_weight

__all__ = ["window_loss", "zero_flow_loss", "accumulated_window_loss", "LOSS_NAMES", "Batchable"]


class Batchable(Protocol):
    """Anything that gives its events as an :class:`EventBatch` (the env's ``envs.windows.Window``)."""

    def batch(self, device=None, dtype: torch.dtype = torch.float32) -> EventBatch: ...


def _spec(spec: LossSpec, loss: str | None) -> LossSpec:
    """``spec``, with the loss named by the older keyword ``loss=`` where one is given."""
    return spec if loss is None or loss == spec.loss else LossSpec.from_options(spec, loss=loss)


def _core(spec: LossSpec, border: float | torch.Tensor) -> dict:
    """The spec as the loss functions' core takes it: every weight by name (the border term's:
    the rule's per-window weight), alpha (L_AT takes none: its logged L_EC is the paper's, as in
    ``at_loss``) and the ramp."""
    alpha = spec.alpha if spec.loss == "hmc" else LossSpec.alpha
    return dict(weights={**spec.to_dict(), "border_penalty": border}, alpha=alpha, border_ramp=spec.border_ramp)


def _events(window: EventBatch | Batchable, device) -> EventBatch:
    return window if isinstance(window, EventBatch) else window.batch(device=device)


def window_loss(
    flow: FlowInput,
    window: EventBatch | Batchable,
    spec: LossSpec = LossSpec(),
    *,
    loss: Literal["hmc", "at"] | None = None,
    flow_scaling: float | None = None,
    zero_flow: torch.Tensor | None = None,
    upsampling: Upsampling = "bilinear",
    reference_times: ReferenceTimes = "window",
    at_normalisation: AtNormalisation = "event_pixels",
) -> LossOutput:
    """The windows' loss under ``spec``, border rule included; for one window, -reward.

    flow: (B, 2, H, W) float, pixels of displacement over the window at full sensor resolution,
        or a list of scales (``hmc_loss``); the graph is kept.
    window: an EventBatch of B windows, or one window that gives its batch (``window.batch()``).
    spec: the loss, its weights and the border rule (default: the env's reward). loss: the older
        way to name the loss ("hmc" or "at"), which replaces the spec's where given.
    flow_scaling: pixels per network unit in the smoothness term (default max(H, W)), a property
        of the flow. upsampling, reference_times, at_normalisation: the readings of ``hmc_loss``.
    zero_flow: (B,) the windows' loss under zero flow (:func:`zero_flow_loss`), the border rule's
        reference, when the caller has it already; computed here otherwise (no graph).
    Returns the LossOutput of ``hmc_loss`` / ``at_loss`` (``loss``: the mean over the B windows,
    ``per_sample``: each window's). A batch of several windows gives each window the loss it has
    alone (the padding is ignored), up to float32 rounding.
    """
    spec = _spec(spec, loss)
    finest = flow if isinstance(flow, torch.Tensor) else list(flow)[-1]
    events = _events(window, finest.device)
    readings = dict(flow_scaling=flow_scaling, upsampling=upsampling, reference_times=reference_times,
                    at_normalisation=at_normalisation)
    penalty: float | torch.Tensor = 0.0
    if spec.border_penalty:
        if zero_flow is None:
            zero_flow = zero_flow_loss(flow, events, spec, **readings).per_sample
        penalty = border_weight(spec.border_penalty, zero_flow.to(finest.dtype))
    return _per_window(flow, events, spec.loss, **_core(spec, penalty), **readings)


def zero_flow_loss(
    like: FlowInput,
    window: EventBatch | Batchable,
    spec: LossSpec = LossSpec(),
    *,
    loss: Literal["hmc", "at"] | None = None,
    flow_scaling: float | None = None,
    upsampling: Upsampling = "bilinear",
    reference_times: ReferenceTimes = "window",
    at_normalisation: AtNormalisation = "event_pixels",
) -> LossOutput:
    """The windows' loss under zero flow, no graph: what the border rule of :func:`window_loss`
    scales with, and the baseline a flow should beat.

    like: a flow as ``window_loss`` takes it; the zero flow has its full resolution, dtype and
    device. The other arguments as in ``window_loss``. Zero flow moves no event, so the border
    rule charges it nothing (events lie inside the image): this is ``window_loss(zeros, window,
    spec)``, in one evaluation of the loss instead of two.
    """
    spec = _spec(spec, loss)
    flows = [like] if isinstance(like, torch.Tensor) else list(like)
    height, width = max(f.shape[2] for f in flows), max(f.shape[3] for f in flows)
    zeros = flows[-1].new_zeros((flows[-1].shape[0], 2, height, width))
    events = _events(window, zeros.device)
    with torch.no_grad():  # the border weight left at 0: the rule would charge nothing
        return _per_window(zeros, events, spec.loss, **_core(spec, 0.0), flow_scaling=flow_scaling,
                           upsampling=upsampling, reference_times=reference_times, at_normalisation=at_normalisation)


def accumulated_window_loss(
    flows: Sequence[FlowInput],
    windows: Sequence[EventBatch],
    spec: LossSpec = LossSpec(),
    *,
    flow_scaling: float | None = None,
    upsampling: Upsampling = "bilinear",
    reference_times: ReferenceTimes = "window",
    at_normalisation: AtNormalisation = "event_pixels",
) -> LossOutput:
    """One loss over the events of K windows (``accumulated_hmc_loss``: Hagenaars' sequential
    learning) under ``spec``, border rule included: its weight is ``border_penalty`` x the K
    windows' accumulated loss under zero flow (no graph), and with the rule on the same weight
    pulls events that left the image back (``outside_weight``). L_HMC only (``spec.loss`` "hmc").

    flows: K items, window k's flow (a tensor or a list of scales); windows: K EventBatch of B
    windows each. flow_scaling and the readings as in :func:`window_loss`.
    """
    if spec.loss != "hmc":
        raise ValueError(f"accumulated_window_loss: the accumulated loss is L_HMC's, not {spec.loss!r}")
    readings = dict(flow_scaling=flow_scaling, upsampling=upsampling, reference_times=reference_times,
                    at_normalisation=at_normalisation)
    penalty: float | torch.Tensor = 0.0
    if spec.border_penalty:
        zeros = [torch.zeros_like(f if isinstance(f, torch.Tensor) else list(f)[-1]) for f in flows]
        with torch.no_grad():
            zero_flow = _accumulated(zeros, windows, outside_weight=0.0, **_core(spec, 0.0), **readings).per_sample
        penalty = border_weight(spec.border_penalty, zero_flow)
    return _accumulated(flows, windows, outside_weight=penalty, **_core(spec, penalty), **readings)
