"""Per-window contrast maximisation: the flow that minimises L_HMC on each window, found by
gradient descent on a coarse grid of flow vectors (no network).

The loss landscape of L_HMC in a dense per-pixel flow is rough (every pixel's flow moves only
the few events on it, and on short windows zero flow is a local minimum: unmoved events at
integer pixels splat onto single pixels). Parametrising the flow by a coarse grid of vectors,
bilinearly upsampled to the image, ties many events to each parameter and smooths the
landscape; coarse-to-fine (e.g. 4x4 then 8x8 cells across the image) starts each level from the
previous one. On the synthetic benchmark this reaches about 0.45x zero flow's AEE at dt = 1
(see docs/results.md), with no ground truth.

Used as a teacher: ``agents/learner.py`` with ``loss="teacher"`` regresses the network onto
these flows (an unsupervised recipe: the teacher sees only the events).
"""

from __future__ import annotations

import dataclasses
from typing import Sequence

import torch
import torch.nn.functional as F

from .events import EventBatch
from .spec import LossSpec
from .window import window_loss, zero_flow_loss

__all__ = ["contrast_maximisation_flow", "CMAX_WEIGHTS"]

#: The solver's loss: the env's reward but for a stronger smoothness term, which regularises
#: the coarse grid of flow vectors.
CMAX_WEIGHTS = LossSpec(lambda_2=1e-2)


def contrast_maximisation_flow(
    events: EventBatch,
    height: int,
    width: int,
    *,
    grids: Sequence[int] = (4, 8),
    steps: int | Sequence[int] = 40,
    lr: float = 0.05,
    flow_scaling: float | None = None,
    weights: LossSpec = CMAX_WEIGHTS,
    return_coarse: bool = False,
    sensor_scales: Sequence[int] | None = None,
    lr_decay: float = 1.0,
    base: torch.Tensor | None = None,
    prior_weight: float | Sequence[float] | torch.Tensor = 0.0,
) -> torch.Tensor:
    """(B, 2, height, width) flow in pixels per window minimising L_HMC of each window.

    events: EventBatch of B windows (tau in [0, 1]). grids: the coarse-to-fine levels, the
    number of cells along the longer image side (the other side in proportion, at least 1).
    steps: Adam steps per level (one int for all, or one per level), lr: its step size in
    pixels. The loss is ``window_loss`` with the spec ``weights`` (L_HMC by default), border rule
    included (default :data:`CMAX_WEIGHTS`). Returns a detached tensor on the events' device, float32; with ``return_coarse``
    the last level's (B, 2, gh, gw) grid instead (the flow is its bilinear upsampling,
    align_corners=False).

    sensor_scales: one integer per level, the coarsening of the *sensor* grid at that level:
    events are splatted at ``(x / s, y / s)`` onto a ``ceil(H / s) x ceil(W / s)`` image and
    the flow divided by s (s = 1: the sensor's own pixels). Coarse pixels gather the events of
    s x s sensor pixels, so the loss stops rewarding a collapse onto single pixels and sees
    larger motions; e.g. ``grids=(4, 8, 16), sensor_scales=(4, 2, 1), steps=(40, 30, 30)``.
    lr_decay: the step size falls geometrically from ``lr`` to ``lr / lr_decay`` over all steps.
    base: optional (B, 2, height, width) flow in pixels that the grid is a residual on (the
    flow is ``base + upsampled grid``, the grid starting at zero), e.g. a network's prediction
    (test-time refinement keeps its detail and corrects it); default none.
    prior_weight: adds ``prior_weight * mean(|grid| / flow_scaling)^2`` over the grid's cells to
    each window's loss, the grid being the correction to ``base`` (or, without one, the flow
    itself): a Gaussian prior that the base (or a still scene) is right, so the solve leaves it
    only where the loss gains more (the loss alone also rewards collapsing the events of a still
    scene); one weight for all windows or one per window ((B,) values); 0: none.
    """
    device = events.x.device
    B = events.x.shape[0]
    scaling = float(max(height, width)) if flow_scaling is None else float(flow_scaling)
    scales = [1] * len(grids) if sensor_scales is None else [int(s) for s in sensor_scales]
    per_level = [int(steps)] * len(grids) if isinstance(steps, int) else [int(k) for k in steps]
    if len(scales) != len(grids) or len(per_level) != len(grids) or min(scales, default=1) < 1:
        raise ValueError(f"grids {list(grids)}, steps {steps} and sensor_scales {sensor_scales} must have one "
                         "entry per level (sensor scales integers >= 1)")
    if base is not None and (return_coarse or tuple(base.shape) != (B, 2, height, width)):
        raise ValueError(f"base must be (B, 2, height, width) = {(B, 2, height, width)} and excludes return_coarse, "
                         f"got {tuple(base.shape)}")
    prior = torch.as_tensor(prior_weight, dtype=torch.float32, device=device).reshape(-1)
    if prior.numel() not in (1, B) or not bool(torch.isfinite(prior).all()) or bool((prior < 0).any()):
        raise ValueError(f"prior_weight must be one finite weight >= 0 or one per window ({B}), got {prior_weight}")
    prior = prior if bool(prior.any()) else None
    total = max(1, sum(per_level))
    coarse = None
    done = 0
    with torch.enable_grad():
        for cells, scale, n_steps in zip(grids, scales, per_level):
            gh = max(1, round(cells * height / max(height, width)))
            gw = max(1, round(cells * width / max(height, width)))
            if coarse is None:
                init = torch.zeros(B, 2, gh, gw, device=device)
            else:
                init = F.interpolate(coarse, size=(gh, gw), mode="bilinear", align_corners=False)
            level_events, (hs, ws) = _coarsen(events, scale), (-(-height // scale), -(-width // scale))
            # the sensor grid s times coarser: flows, the flow scaling and the ramp in its pixels
            level = dict(spec=dataclasses.replace(weights, border_ramp=weights.border_ramp / scale),
                         flow_scaling=scaling / scale)
            zero = None
            if weights.border_penalty:  # the border rule's reference, once per level
                zero = zero_flow_loss(torch.zeros(B, 2, hs, ws, device=device), level_events, **level).per_sample
            offset = None
            if base is not None:
                offset = base.float() if scale == 1 else F.interpolate(base.float(), size=(hs, ws), mode="area")
                offset = offset / scale
            param = init.clone().requires_grad_()
            optimizer = torch.optim.Adam([param], lr=lr)
            for _ in range(n_steps):
                for group in optimizer.param_groups:
                    group["lr"] = lr * lr_decay ** (-done / total)
                flow = F.interpolate(param, size=(hs, ws), mode="bilinear", align_corners=False) / scale
                if offset is not None:
                    flow = flow + offset
                loss = window_loss(flow, level_events, zero_flow=zero, **level).per_sample.sum()
                if prior is not None:
                    loss = loss + (prior * (param / scaling).pow(2).sum(1).mean(dim=(1, 2))).sum()
                optimizer.zero_grad(set_to_none=True)
                loss.backward()
                optimizer.step()
                done += 1
            coarse = param.detach()
    if coarse is None:
        coarse = torch.zeros(B, 2, 1, 1, device=device)
    if return_coarse:
        return coarse
    flow = F.interpolate(coarse, size=(height, width), mode="bilinear", align_corners=False)
    return flow if base is None else base.float().detach() + flow


def _coarsen(events: EventBatch, scale: int) -> EventBatch:
    """The events on a sensor grid ``scale`` times coarser (coordinates divided by it)."""
    if scale == 1:
        return events
    return EventBatch(events.x / scale, events.y / scale, events.tau, events.p, events.mask)
