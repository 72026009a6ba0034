"""Images of warped events: per-polarity count and average-timestamp images (REFERENCE sec. 5).

All images of a batch (every batch element, every reference time, both polarities, both the
count and the timestamp-weighted sum) are built by a single call of the splatting routine.
"""

from __future__ import annotations

from typing import Sequence

import torch

from .splat import splat_into
from .warp import warp_events

__all__ = ["warped_event_images", "average_timestamp_images"]


def warped_event_images(
    x: torch.Tensor,
    y: torch.Tensor,
    t: torch.Tensor,
    p: torch.Tensor,
    mask: torch.Tensor,
    u: torch.Tensor,
    height: int,
    width: int,
    references: Sequence[float] = (0.0, 1.0),
    span: float = 1.0,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Count images C_P and timestamp sums A_P for every reference time, both polarities.

    x, y: (B, N) float pixels (unwarped). t: (B, N) float, time in windows (tau in [0, 1];
    k + tau in the accumulated variant). p: (B, N) float, ``p > 0`` is ON. mask: (B, N) bool.
    u: (B, N, 2) float, per-event flow in pixels per window.
    references: R reference times s, in windows. span: the time span the weights are
    normalised by (1 per window; K for K accumulated windows).
    Returns ``count`` and ``stamp``, each (B, R, 2, H, W) in u's dtype, polarity index 0 = ON,
    1 = OFF:
      ``count[b, r, P] = sum_{i in P} k(. - x'_i)``                   (C_P)
      ``stamp[b, r, P] = sum_{i in P} k(. - x'_i) (1 - |s_r - t_i| / span)``   (A_P)
    with x'_i warped to s_r by eq. 12.
    """
    B, N = x.shape
    R = len(references)
    dtype = u.dtype
    x, y, t = x.to(dtype), y.to(dtype), t.to(dtype)
    ref = torch.tensor(list(references), dtype=dtype, device=u.device).view(1, R, 1)
    tt = t.unsqueeze(1)  # (B, 1, N)
    xw, yw = warp_events(x.unsqueeze(1), y.unsqueeze(1), tt, u.unsqueeze(1), ref)  # (B, R, N)
    closeness = 1 - (ref - tt).abs() / span  # (B, R, N)
    values = torch.stack([torch.ones_like(closeness), closeness], dim=-1)  # (B, R, N, 2)
    off = (p <= 0).long().unsqueeze(1)  # (B, 1, N)
    image = (torch.arange(B, device=u.device).view(B, 1, 1) * R
             + torch.arange(R, device=u.device).view(1, R, 1)) * 2 + off
    out = splat_into(xw, yw, values, image, B * R * 2, height, width, mask.unsqueeze(1))
    out = out.view(B, R, 2, height, width, 2)
    return out[..., 0], out[..., 1]


def average_timestamp_images(count: torch.Tensor, stamp: torch.Tensor) -> torch.Tensor:
    """Average-timestamp image T_P = A_P / (C_P + 1e-9) (eq. 13); same shape as the inputs."""
    return stamp / (count + 1e-9)
