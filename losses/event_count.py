"""Event-count loss L_EC(s) (docs/method.md, "Losses", eqs. 15-16)."""

from __future__ import annotations

import torch

__all__ = ["event_count_loss"]


def event_count_loss(count: torch.Tensor, alpha: float = 0.6) -> torch.Tensor:
    """L_EC(s) = N / sum_x exp(-alpha C_+(x)) + N / sum_x exp(-alpha C_-(x)) - 2, N = H*W.

    count: (..., 2, H, W) float, per-polarity count images C_P (non-negative).
    alpha: 0.6 (paper). Returns (...) float; 0 for an empty window, grows as events disperse.
    """
    n_pixels = count.shape[-1] * count.shape[-2]
    denom = torch.exp(-alpha * count).sum(dim=(-2, -1))  # (..., 2), eq. 15
    return (n_pixels / denom).sum(dim=-1) - 2  # eq. 16
