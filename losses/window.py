"""The loss of a window as the env's reward scores it: L_HMC (or L_AT) plus the border rule.

One function for every consumer (docs/method.md, "Losses"): the env's reward is
``-window_loss(action, window)``; the learner calls it on a batch of windows with gradients; the
evaluation's L_HMC column and the contrast-maximisation solver (the teacher) call it too. The
border rule is one of the :class:`LossWeights`: ``border_penalty`` x the window's loss under zero
flow x the (ramped) share of its events the flow pushes out of the image.
"""

from __future__ import annotations

from typing import Literal, Protocol

import torch

from .events import EventBatch
from .hmc import (
    AtNormalisation,
    FlowInput,
    LossOutput,
    LossWeights,
    ReferenceTimes,
    Upsampling,
    _check_choice,
    at_loss,
    hmc_loss,
)

__all__ = ["window_loss", "zero_flow_loss", "LOSS_NAMES", "Batchable"]

#: The losses a window can be scored with: L_HMC (eq. 17) or the baseline L_AT (eq. 14 + smoothing).
LOSS_NAMES = ("hmc", "at")
_LOSSES = {"hmc": hmc_loss, "at": at_loss}


class Batchable(Protocol):
    """Anything that gives its events as an :class:`EventBatch` (the env's ``envs.windows.Window``)."""

    def batch(self, device=None, dtype: torch.dtype = torch.float32) -> EventBatch: ...


def window_loss(
    flow: FlowInput,
    window: EventBatch | Batchable,
    weights: LossWeights = LossWeights(),
    *,
    loss: Literal["hmc", "at"] = "hmc",
    flow_scaling: float | None = None,
    zero_flow: torch.Tensor | None = None,
    upsampling: Upsampling = "bilinear",
    reference_times: ReferenceTimes = "window",
    at_normalisation: AtNormalisation = "event_pixels",
) -> LossOutput:
    """The windows' loss with ``weights``, border rule included; for one window, -reward.

    flow: (B, 2, H, W) float, pixels of displacement over the window at full sensor resolution,
        or a list of scales (``hmc_loss``); the graph is kept.
    window: an EventBatch of B windows, or one window that gives its batch (``window.batch()``).
    weights: lambda_1, lambda_2, alpha and the border rule (default: the env's reward).
    loss: "hmc" or "at". flow_scaling: pixels per network unit in the smoothness term (default
        max(H, W)). upsampling, reference_times, at_normalisation: the readings of ``hmc_loss``.
    zero_flow: (B,) the windows' loss under zero flow (:func:`zero_flow_loss`), the border rule's
        reference, when the caller has it already; computed here otherwise (no graph).
    Returns the LossOutput of ``hmc_loss`` / ``at_loss`` (``loss``: the mean over the B windows,
    ``per_sample``: each window's). A batch of several windows gives each window the loss it has
    alone (the padding is ignored), up to float32 rounding.
    """
    _check_choice("loss", loss, LOSS_NAMES)
    finest = flow if isinstance(flow, torch.Tensor) else list(flow)[-1]
    events = window if isinstance(window, EventBatch) else window.batch(device=finest.device)
    readings = dict(flow_scaling=flow_scaling, upsampling=upsampling, reference_times=reference_times,
                    at_normalisation=at_normalisation)
    penalty: float | torch.Tensor = 0.0
    if weights.border_penalty:
        if zero_flow is None:
            zero_flow = zero_flow_loss(flow, events, weights, loss=loss, **readings).per_sample
        penalty = weights.border_penalty * zero_flow.to(finest.dtype)
    return _LOSSES[loss](flow, events, border_penalty=penalty, **readings, **weights.of(loss))


def zero_flow_loss(
    like: FlowInput,
    window: EventBatch | Batchable,
    weights: LossWeights = LossWeights(),
    *,
    loss: Literal["hmc", "at"] = "hmc",
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
    weights)``, in one evaluation of the loss instead of two.
    """
    _check_choice("loss", loss, LOSS_NAMES)
    flows = [like] if isinstance(like, torch.Tensor) else list(like)
    height, width = max(f.shape[2] for f in flows), max(f.shape[3] for f in flows)
    zeros = flows[-1].new_zeros((flows[-1].shape[0], 2, height, width))
    events = window if isinstance(window, EventBatch) else window.batch(device=zeros.device)
    with torch.no_grad():  # border_penalty left at 0: the rule would charge nothing
        return _LOSSES[loss](zeros, events, flow_scaling=flow_scaling, upsampling=upsampling,
                             reference_times=reference_times, at_normalisation=at_normalisation, **weights.of(loss))

