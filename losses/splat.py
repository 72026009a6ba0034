"""Bilinear splatting: the one routine behind every image of warped events (REFERENCE sec. 5).

Kernel ``k(dx, dy) = max(0, 1 - |dx|) * max(0, 1 - |dy|)``: a point at (x, y) spreads onto
the (up to) 4 pixels around it; corners outside the image get weight 0 (they are dropped, the
point still counts on its other corners). The same routine serves the count and
average-timestamp images (both polarities, both reference times in one call, see ``iwe.py``)
and the forward warp of a flow field (``warp.py``, REFERENCE eq. 9).
"""

from __future__ import annotations

import torch

__all__ = ["bilinear_corners", "splat_into", "bilinear_splat"]


def bilinear_corners(
    x: torch.Tensor, y: torch.Tensor, height: int, width: int
) -> tuple[torch.Tensor, torch.Tensor]:
    """The 4 pixels around each point and their bilinear weights.

    x, y: (...) float, pixels (x = column, y = row).
    Returns ``index`` (..., 4) int64, flat pixel index ``row * width + col`` (0 for dropped
    corners), and ``weight`` (..., 4) float, ``k(dx, dy)``, exactly 0 for corners outside the
    image. Corner order: (x0, y0), (x0+1, y0), (x0, y0+1), (x0+1, y0+1), x0 = floor(x).
    Differentiable in x and y through ``weight``.
    """
    x0f = torch.floor(x)
    y0f = torch.floor(y)
    fx = (x - x0f).unsqueeze(-1)  # (..., 1) in [0, 1]
    fy = (y - y0f).unsqueeze(-1)
    x0 = x0f.long().unsqueeze(-1)
    y0 = y0f.long().unsqueeze(-1)
    step = torch.tensor([0, 1], device=x.device)
    cx = x0 + step  # (..., 2) columns x0, x0+1
    cy = y0 + step  # (..., 2) rows y0, y0+1
    wx = torch.cat([1 - fx, fx], dim=-1) * ((cx >= 0) & (cx < width))
    wy = torch.cat([1 - fy, fy], dim=-1) * ((cy >= 0) & (cy < height))
    weight = (wy.unsqueeze(-1) * wx.unsqueeze(-2)).flatten(-2)  # (..., 4)
    index = (cy.clamp(0, height - 1).unsqueeze(-1) * width + cx.clamp(0, width - 1).unsqueeze(-2))
    return index.flatten(-2), weight


def splat_into(
    x: torch.Tensor,
    y: torch.Tensor,
    values: torch.Tensor,
    image_index: torch.Tensor | None,
    num_images: int,
    height: int,
    width: int,
    mask: torch.Tensor | None = None,
) -> torch.Tensor:
    """Bilinear-splat points into a stack of images with one index_add.

    x, y: (...) float pixels. values: (..., C) float, what each point carries (times k).
    image_index: (...) int64 in [0, num_images), which image each point goes to (None: all 0).
    mask: (...) bool, False points contribute nothing (None: all valid).
    Returns (num_images, height, width, C) in ``values.dtype``; differentiable in x, y, values.
    """
    index, weight = bilinear_corners(x, y, height, width)
    if mask is not None:
        weight = weight * mask.unsqueeze(-1)
    if image_index is not None:
        index = index + (image_index * (height * width)).unsqueeze(-1)
    source = weight.unsqueeze(-1) * values.unsqueeze(-2)  # (..., 4, C)
    C = values.shape[-1]
    out = values.new_zeros(num_images * height * width, C)
    out = out.index_add(0, index.reshape(-1), source.reshape(-1, C))
    return out.view(num_images, height, width, C)


def bilinear_splat(
    x: torch.Tensor,
    y: torch.Tensor,
    values: torch.Tensor,
    height: int,
    width: int,
    mask: torch.Tensor | None = None,
) -> torch.Tensor:
    """Splat B sets of N points carrying C values each into B images.

    x, y: (B, N) float, pixels. values: (B, N, C) float. mask: (B, N) bool or None.
    Returns (B, C, height, width), ``out[b, c, r, q] = sum_i k(q - x_bi, r - y_bi) values[b, i, c]``
    over valid points; out-of-image corners are dropped.
    """
    if x.shape != y.shape or x.ndim != 2 or values.shape[:2] != x.shape or values.ndim != 3:
        raise ValueError(
            f"bilinear_splat: need x, y (B, N) and values (B, N, C); got x {tuple(x.shape)}, "
            f"y {tuple(y.shape)}, values {tuple(values.shape)}"
        )
    if mask is not None and mask.shape != x.shape:
        raise ValueError(f"bilinear_splat: mask shape {tuple(mask.shape)} != x shape {tuple(x.shape)}")
    B, N = x.shape
    image_index = torch.arange(B, device=x.device).unsqueeze(1).expand(B, N)
    out = splat_into(x, y, values, image_index, B, height, width, mask)
    return out.permute(0, 3, 1, 2)
