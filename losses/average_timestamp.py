"""Average-timestamp loss L_AT(s) (docs/method.md, "Losses", eqs. 13-14)."""

from __future__ import annotations

import torch

from .iwe import average_timestamp_images

__all__ = ["average_timestamp_loss"]


def average_timestamp_loss(count: torch.Tensor, stamp: torch.Tensor) -> torch.Tensor:
    """L_AT(s) = (sum_x T_+^2 + sum_x T_-^2) / (N_nz + 1e-9).

    count, stamp: (..., 2, H, W) float, C_P and A_P per polarity (see ``iwe.py``).
    Returns (...) float. N_nz = number of pixels with C_+ + C_- > 0 (the paper's eq. 14 prints
    the bare sum; we divide by N_nz as both TU Delft implementations do). 0 for no events.
    """
    T = average_timestamp_images(count, stamp)  # eq. 13
    total = (T * T).sum(dim=(-3, -2, -1))
    n_nz = (count.sum(dim=-3) > 0).sum(dim=(-2, -1)).to(count.dtype)
    return total / (n_nz + 1e-9)  # eq. 14, normalised
