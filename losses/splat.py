"""Bilinear splatting: the one routine behind every image of warped events (docs/method.md, "Losses").

Kernel ``k(dx, dy) = max(0, 1 - |dx|) * max(0, 1 - |dy|)``: a point at (x, y) spreads onto the
(up to) 4 pixels around it; corners outside the image get weight 0 (they are dropped, the point
still counts on its other corners). The same routine serves the count and average-timestamp
images (every batch element, both reference times, both polarities, counts and timestamp sums
in one ``scatter_add``, see ``iwe.py``) and the forward warp of a flow field (``warp.py``,
eq. 9).

Layout. Points come in *rows* (the leading dims, e.g. batch x reference time); each row owns a
stack of ``images_per_row`` *padded* images of shape (H + 2, W + 2), pixel (row r, col q)
stored at (r + 1, q + 1). A point with -1 <= x < W and -1 <= y < H has all 4 corners inside
the padded image; corners outside the real image land on the 1-pixel ring, which is cropped
away (= dropped). Points farther out get weight 0. No per-corner mask is needed, and one
``scatter_add`` along the last dim runs the rows in parallel.
"""

from __future__ import annotations

import math

import torch

__all__ = ["padded_corners", "splat_rows", "crop_padding", "bilinear_splat"]


def padded_corners(
    x: torch.Tensor,
    y: torch.Tensor,
    height: int,
    width: int,
    image_index: torch.Tensor | None = None,
    valid: torch.Tensor | None = None,
    images_per_row: int = 1,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Corner pixels and separable bilinear weights of points, in the padded layout.

    x, y: (..., N) float, pixels (x = column, y = row). image_index: (..., N) (broadcastable),
    which image of its row's stack of ``images_per_row`` each point goes to (None: 0). valid: (..., N) bool
    (broadcastable), False points get weight 0.
    Returns (corner-major layout: every slice along the corner dim is contiguous)
      ``index`` (..., 4, N) int64, flat index into the row's (images, H + 2, W + 2) stack of
      the corners (x0, y0), (x0+1, y0), (x0, y0+1), (x0+1, y0+1), x0 = floor(x), y0 = floor(y);
      ``wx`` (..., 2, N) = (1 - fx, fx), fx = x - x0;
      ``wy`` (..., 2, N) = (1 - fy, fy) * inside, fy = y - y0;
      ``inside`` (..., N) bool = (-1 <= x < W) & (-1 <= y < H) & valid.
    The corner weight is ``k = wy[a] * wx[b]`` (corner 2a + b), which equals
    ``max(0, 1 - |dx|) * max(0, 1 - |dy|)`` exactly. Differentiable in x, y through wx, wy.
    """
    x0 = torch.floor(x)
    y0 = torch.floor(y)
    fx = x - x0
    fy = y - y0
    xc = x0.clamp(-1, width - 1)
    yc = y0.clamp(-1, height - 1)
    inside = (xc == x0) & (yc == y0)
    if valid is not None:
        inside = inside & valid
    hp, wp = height + 2, width + 2
    row = yc + 1 if image_index is None else yc + (image_index.to(x.dtype) * hp + 1)
    exact = 2**24 if x.dtype != torch.float64 else 2**53
    if images_per_row * hp * wp < exact:  # float arithmetic on integers is exact here
        base = (row * wp + (xc + 1)).long()
    else:
        base = row.long() * wp + (xc.long() + 1)
    index = base.unsqueeze(-2) + torch.tensor([[0], [1], [wp], [wp + 1]], device=x.device)
    inside_f = inside.to(x.dtype)
    wx = torch.stack([1 - fx, fx], dim=-2)
    fy_in = fy * inside_f
    wy = torch.stack([inside_f - fy_in, fy_in], dim=-2)
    return index, wx, wy, inside


def splat_rows(
    index: torch.Tensor,
    wx: torch.Tensor,
    wy: torch.Tensor,
    values: torch.Tensor,
    images_per_row: int,
    height: int,
    width: int,
) -> torch.Tensor:
    """Splat with the corners of ``padded_corners``, all channels in one scatter_add.

    index: (..., 4, N); wx, wy: (..., 2, N); values: (..., C, N) float, what each point carries.
    Returns (..., C, images_per_row, H + 2, W + 2) padded images,
    ``img[..., c, :] = sum_points k(. - point) * values[..., c, point]``.
    Differentiable (autograd) in wx, wy and values.
    """
    lead = index.shape[:-2]
    N = index.shape[-1]
    C = values.shape[-2]
    rows = math.prod(lead)
    k = (wy.unsqueeze(-2) * wx.unsqueeze(-3)).reshape(rows, 1, 4, N)  # corner 2a + b
    src = (k * values.reshape(rows, C, 1, N)).reshape(rows, C, 4 * N)
    idx = index.reshape(rows, 1, 4 * N).expand(rows, C, 4 * N)
    size = images_per_row * (height + 2) * (width + 2)
    out = torch.zeros(rows, C, size, dtype=src.dtype, device=src.device).scatter_add(2, idx, src)
    return out.view(*lead, C, images_per_row, height + 2, width + 2)


def crop_padding(image: torch.Tensor) -> torch.Tensor:
    """(..., H + 2, W + 2) padded -> (..., H, W) view of the real image (drops the ring)."""
    return image[..., 1:-1, 1:-1]


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
    over valid points; out-of-image corners are dropped. Differentiable in x, y and values.
    """
    if x.shape != y.shape or x.ndim != 2 or values.ndim != 3 or values.shape[:2] != x.shape:
        raise ValueError(
            f"bilinear_splat: need x, y (B, N) and values (B, N, C); got x {tuple(x.shape)}, "
            f"y {tuple(y.shape)}, values {tuple(values.shape)}"
        )
    if mask is not None and mask.shape != x.shape:
        raise ValueError(f"bilinear_splat: mask shape {tuple(mask.shape)} != x shape {tuple(x.shape)}")
    index, wx, wy, _ = padded_corners(x, y, height, width, None, mask)
    images = splat_rows(index, wx, wy, values.transpose(1, 2), 1, height, width)
    return crop_padding(images[:, :, 0])
