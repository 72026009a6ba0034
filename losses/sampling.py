"""Per-event flow: bilinear sampling of a flow field at event coordinates (REFERENCE sec. 5)."""

from __future__ import annotations

import torch

from .splat import bilinear_corners

__all__ = ["sample_flow"]


def sample_flow(flow: torch.Tensor, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """Bilinearly sample ``flow`` at (x, y).

    flow: (B, 2, H, W) float, pixels per window. x, y: (B, N) float, pixels.
    Returns (B, N, 2) float (u_x, u_y), in flow's units and dtype.

    Exact at integer pixels (the weight on the event's own pixel is exactly 1). Coordinates
    outside the image are clamped to [0, W-1] x [0, H-1] first ("border" rule), so an event
    off the sensor takes the flow of the nearest border pixel. Differentiable in flow.
    """
    B, _, H, W = flow.shape
    x = x.to(flow.dtype).clamp(0, W - 1)
    y = y.to(flow.dtype).clamp(0, H - 1)
    index, weight = bilinear_corners(x, y, H, W)  # (B, N, 4); corner at W or H has weight 0
    offset = (torch.arange(B, device=flow.device) * (H * W)).view(B, 1, 1)
    table = flow.permute(0, 2, 3, 1).reshape(B * H * W, 2)
    corners = table.index_select(0, (index + offset).reshape(-1)).view(*index.shape, 2)
    return (corners * weight.unsqueeze(-1)).sum(dim=-2)
