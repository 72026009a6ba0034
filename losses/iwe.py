"""Images of warped events: per-polarity count and average-timestamp images (docs/method.md, "Losses").

All images of a batch (every batch element, every reference time, both polarities, counts C_P
and timestamp sums A_P) are built by one call of the splatting routine (one scatter_add).
"""

from __future__ import annotations

from typing import Sequence

import torch

from .events import EventBatch
from .splat import crop_padding, padded_corners, splat_rows
from .warp import warp_events

__all__ = ["warped_corners", "warped_event_images", "average_timestamp_images"]


def warped_corners(events: EventBatch, u: torch.Tensor, height: int, width: int, references: Sequence[float],
                   span: float):
    """Warp every event to every reference time (eq. 12) and find its splat corners.

    Shapes as in ``warped_event_images``. Returns (index, wx, wy, inside, closeness, dt):
    index (B, R, 4, N), wx, wy (B, R, 2, N), inside (B, R, N) as in ``padded_corners``, rows
    (batch, reference), 2 images per row (polarity ON, OFF); closeness (B, R, N) =
    1 - |s_r - t_i| / span, the timestamp weight; dt (B, R, N) = s_r - t_i (= d x' / d u).
    """
    x, y, t, p, mask = events
    R = len(references)
    dtype = u.dtype
    ref = torch.tensor(list(references), dtype=dtype, device=u.device).view(1, R, 1)
    t = t.to(dtype).unsqueeze(1)
    xw, yw = warp_events(x.to(dtype).unsqueeze(1), y.to(dtype).unsqueeze(1), t,
                         u.unsqueeze(1), ref)  # eq. 12, (B, R, N)
    dt = ref - t
    closeness = 1 - dt.abs() / span
    off = (p <= 0).unsqueeze(1)  # (B, 1, N): image 0 = ON, 1 = OFF
    index, wx, wy, inside = padded_corners(xw, yw, height, width, off, mask.unsqueeze(1), 2)
    return index, wx, wy, inside, closeness, dt


def splat_counts_and_stamps(index, wx, wy, closeness, height, width) -> torch.Tensor:
    """(B, R, 2 [count, stamp], 2 [ON, OFF], H + 2, W + 2) padded images, one scatter_add."""
    values = torch.stack([torch.ones_like(closeness), closeness], dim=-2)  # (B, R, 2, N)
    return splat_rows(index, wx, wy, values, 2, height, width)


def warped_event_images(
    events: EventBatch,
    u: torch.Tensor,
    height: int,
    width: int,
    references: Sequence[float] = (0.0, 1.0),
    span: float = 1.0,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Count images C_P and timestamp sums A_P for every reference time, both polarities.

    events: the B windows' events (unwarped); their ``tau`` is the time in windows (in [0, 1];
    k + tau for window k of the accumulated variant).
    u: (B, N, 2) float, per-event flow in pixels per window.
    references: R reference times s, in windows. span: the time span the weights are
    normalised by (1 per window; K for K accumulated windows).
    Returns ``count`` and ``stamp``, each (B, R, 2, H, W) in u's dtype, polarity index 0 = ON,
    1 = OFF:
      ``count[b, r, P] = sum_{i in P} k(. - x'_i)``                          (C_P)
      ``stamp[b, r, P] = sum_{i in P} k(. - x'_i) (1 - |s_r - t_i| / span)``  (A_P)
    with x'_i warped to s_r by eq. 12. Differentiable (plain autograd) in u; the losses use
    the fused backward of ``image_terms.py``.
    """
    index, wx, wy, _, closeness, _ = warped_corners(events, u, height, width, references, span)
    images = crop_padding(splat_counts_and_stamps(index, wx, wy, closeness, height, width))
    return images[:, :, 0], images[:, :, 1]


def average_timestamp_images(count: torch.Tensor, stamp: torch.Tensor) -> torch.Tensor:
    """Average-timestamp image T_P = A_P / (C_P + 1e-9) (eq. 13); same shape as the inputs."""
    return stamp / (count + 1e-9)
