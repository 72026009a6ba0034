"""The unrolled finish: K gradient steps on the window's loss, taken on a coarse correction to a
proposed flow, differentiable with respect to the proposal (``create_graph``), so that training can
take its loss after the finish and teach the network to be the proposal a short solve lands right
from (docs/finish.md)::

    finished = unrolled_finish(proposal, batch, steps=3, lr=0.5 * frames)   # graph kept
    loss = window_loss(finished, batch).loss                                 # then backward()

Each step: ``r <- r - lr_k * g / mean|g|`` with ``g`` the gradient of the windows' summed loss with
respect to the correction grid ``r`` (``grid`` cells along the longer side, bilinearly upsampled
and added to the proposal), each window's gradient normalised by its own mean magnitude (so ``lr``
is the mean move of a cell in pixels, whatever the loss's scale), ``lr_k`` falling linearly from
``lr`` to ``lr / steps``. Plain gradient steps rather than Adam: the same update is then a smooth
function of the proposal whose derivative autograd takes through every step.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from .events import EventBatch
from .spec import LossSpec
from .window import window_loss, zero_flow_loss

__all__ = ["unrolled_finish"]

#: the normalisation's floor: a window without gradient (no events) does not move
_EPS = 1e-12


def unrolled_finish(
    proposal: torch.Tensor,
    events: EventBatch,
    *,
    steps: int,
    lr: float | torch.Tensor,
    grid: int = 16,
    weights: LossSpec = LossSpec(),
    flow_scaling: float | None = None,
    create_graph: bool = True,
) -> torch.Tensor:
    """(B, 2, H, W) the proposal finished by ``steps`` normalised gradient steps on a ``grid``-cell
    correction (module docstring). proposal: (B, 2, H, W) pixels per window (its graph, if any,
    is kept); events: the B windows; lr: pixels per step, one number or (B,) per window (e.g. 0.5
    times each window's length in frames); weights, flow_scaling: the loss (the env's reward by
    default; flow scaling max(H, W)). create_graph: False for a finish at test time (no graph,
    the same flow)."""
    if steps < 0:
        raise ValueError(f"unrolled_finish: steps must be >= 0, got {steps}")
    if steps == 0:
        return proposal
    B, _, height, width = proposal.shape
    gh = max(1, round(grid * height / max(height, width)))
    gw = max(1, round(grid * width / max(height, width)))
    scaling = float(max(height, width)) if flow_scaling is None else float(flow_scaling)
    rate = torch.as_tensor(lr, dtype=proposal.dtype, device=proposal.device).reshape(-1, 1, 1, 1)
    zero = zero_flow_loss(proposal.detach(), events, weights, flow_scaling=scaling).per_sample
    correction = proposal.new_zeros((B, 2, gh, gw), requires_grad=True)
    with torch.enable_grad():
        for k in range(steps):
            flow = proposal + F.interpolate(correction, size=(height, width), mode="bilinear", align_corners=False)
            loss = window_loss(flow, events, weights, flow_scaling=scaling, zero_flow=zero).per_sample.sum()
            (gradient,) = torch.autograd.grad(loss, correction, create_graph=create_graph)
            norm = gradient.abs().mean(dim=(1, 2, 3), keepdim=True).clamp_min(_EPS)
            correction = correction - rate * (1.0 - k / steps) * gradient / norm
            if not create_graph:
                correction = correction.detach().requires_grad_()
    finished = proposal + F.interpolate(correction, size=(height, width), mode="bilinear", align_corners=False)
    return finished if create_graph else finished.detach()
