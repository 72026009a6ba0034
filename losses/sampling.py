"""Per-event flow: bilinear sampling of a flow field at event coordinates (docs/method.md, "Losses")."""

from __future__ import annotations

import torch

__all__ = ["sample_flow"]


def sample_flow(flow: torch.Tensor, x: torch.Tensor, y: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
    """Bilinearly sample ``flow`` at (x, y).

    flow: (B, 2, H, W) float, pixels per window. x, y: (B, N) float, pixels.
    Returns (B, N, 2) float (u_x, u_y), in flow's units and dtype.

    Exact at integer pixels (the event's own pixel gets weight exactly 1; when every
    coordinate is an integer a single gather per event is used). Coordinates outside the image
    are clamped to [0, W-1] x [0, H-1] first ("border" rule), so an event off the sensor takes
    the flow of the nearest border pixel. Differentiable in flow. mask: optional (B, N) bool;
    padding events (False) may hold any coordinates, NaN included, and get pixel (0, 0)'s flow
    (callers must not use it). No compiled kernel: one gained under 10 % of a training or env
    step (docs/performance.md).
    """
    B, _, H, W = flow.shape
    hw = H * W
    if mask is not None:  # padding slots may hold anything, NaN included: sample pixel (0, 0) there
        x, y = torch.where(mask, x, 0), torch.where(mask, y, 0)
    x = x.to(flow.dtype).clamp(0, W - 1)
    y = y.to(flow.dtype).clamp(0, H - 1)
    table = flow.reshape(-1)  # channel-major: index b * 2HW + c * HW + pixel
    chan = (torch.arange(B, device=flow.device) * (2 * hw)).view(B, 1, 1) + torch.tensor(
        [0, hw], device=flow.device
    )  # (B, 1, 2)
    x0f, y0f = torch.floor(x), torch.floor(y)
    if bool(torch.equal(x0f, x) and torch.equal(y0f, y)):  # integer pixels: one gather
        pix = (y.long() * W + x.long()).unsqueeze(-1) + chan  # (B, N, 2)
        return table.index_select(0, pix.reshape(-1)).view(B, -1, 2)
    fx, fy = (x - x0f).unsqueeze(1), (y - y0f).unsqueeze(1)  # (B, 1, N)
    x0, y0 = x0f.long(), y0f.long()
    x1, y1 = (x0 + 1).clamp(max=W - 1), (y0 + 1).clamp(max=H - 1)  # weight 0 there if clamped
    corners = torch.stack([y0 * W + x0, y0 * W + x1, y1 * W + x0, y1 * W + x1], dim=1)  # (B, 4, N)
    weight = torch.cat([(1 - fy) * (1 - fx), (1 - fy) * fx, fy * (1 - fx), fy * fx], dim=1)
    idx = corners.unsqueeze(-1) + chan.unsqueeze(1)  # (B, 4, N, 2)
    vals = table.index_select(0, idx.reshape(-1)).view(*idx.shape)
    return (vals * weight.unsqueeze(-1)).sum(dim=1)
