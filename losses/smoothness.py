"""Charbonnier smoothness prior on the flow, where there are events (REFERENCE sec. 5).

Per-component form: for each of 4 neighbour directions (right, down, down-right, up-right) and
each flow component, ``rho(d) = sqrt(d^2 + eps^2)`` of the neighbour difference d of the flow in
network units (u / flow_scaling), summed over pairs whose two pixels both hold an input event
and over both components, then averaged over the 4 directions. (Hagenaars' code squares the sum
of the x and y differences instead; we take the per-component form.)
"""

from __future__ import annotations

import torch

__all__ = ["event_pixel_mask", "charbonnier_smoothness"]


def event_pixel_mask(
    x: torch.Tensor, y: torch.Tensor, mask: torch.Tensor, height: int, width: int
) -> torch.Tensor:
    """Pixels holding at least one (unwarped) valid event.

    x, y: (B, N) float pixels; mask: (B, N) bool. Returns (B, height, width) bool.
    Coordinates are rounded to the nearest pixel (``torch.round``, ties to even), which is the
    identity for raw integer events and nearest-pixel for rectified float ones; events that
    round outside the image are ignored.
    """
    B, N = x.shape
    xi = torch.round(x).long()
    yi = torch.round(y).long()
    keep = mask & (xi >= 0) & (xi < width) & (yi >= 0) & (yi < height)
    hw = height * width
    flat = torch.arange(B, device=x.device).view(B, 1) * hw + yi * width + xi
    flat = torch.where(keep, flat, B * hw)  # dump slot for dropped events
    out = torch.zeros(B * hw + 1, dtype=torch.bool, device=x.device)
    out[flat.reshape(-1)] = True
    return out[:-1].view(B, height, width)


def _pairs(a: torch.Tensor):
    """Both ends of each neighbour pair for the 4 directions; a is (..., H, W)."""
    return (
        (a[..., :, :-1], a[..., :, 1:]),  # right
        (a[..., :-1, :], a[..., 1:, :]),  # down
        (a[..., :-1, :-1], a[..., 1:, 1:]),  # down-right
        (a[..., 1:, :-1], a[..., :-1, 1:]),  # up-right
    )


def charbonnier_smoothness(
    flow: torch.Tensor, event_mask: torch.Tensor, flow_scaling: float, eps: float = 1e-3
) -> torch.Tensor:
    """L_smooth per batch element.

    flow: (B, 2, H, W) float, pixels per window. event_mask: (B, H, W) bool (see
    ``event_pixel_mask``). flow_scaling: pixels per network unit (default in the losses:
    max(H, W)). eps: Charbonnier epsilon, 1e-3.
    Returns (B,) float: sum over masked pairs and components of sqrt(d^2 + eps^2), averaged over
    the 4 directions.
    """
    f = flow / flow_scaling
    m = event_mask.unsqueeze(1).to(flow.dtype)  # (B, 1, H, W)
    total = flow.new_zeros(flow.shape[0])
    for (fa, fb), (ma, mb) in zip(_pairs(f), _pairs(m)):
        rho = torch.sqrt((fb - fa) ** 2 + eps * eps)
        total = total + (rho * (ma * mb)).sum(dim=(1, 2, 3))
    return total / 4
