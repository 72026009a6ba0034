"""Network inputs built from one window's events (docs/method.md, "Windows and network inputs").

- :func:`count_image`: paper eq. 2, (2, H, W) float32; channel 0 counts ON events, channel 1
  OFF events, per pixel.
- :func:`voxel_grid`: (B, H, W) float32, signed polarity spread bilinearly in time over B bins
  at position ``tau * (B - 1)``.
- :func:`event_mask`: (H, W) bool, pixels with at least one event.
- :func:`count_time_image`: (4, H, W) float32, Zhu et al.'s EV-FlowNet input: the count image
  and, per polarity, the time of the pixel's latest event.

:data:`OBSERVATIONS` lists the images that are network inputs (the env's image observations):
each one's channels, bounds and builder.

Each has a numpy version (for the env) and a torch version (``*_torch``, batched, for
training on a device) that agree exactly: both accumulate in float64 or integers before the
float32 cast, so the results are bit-identical.

Coordinates that are floats (rectified events) are rounded to the nearest pixel.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np
import torch

__all__ = [
    "count_image",
    "voxel_grid",
    "event_mask",
    "count_time_image",
    "count_image_torch",
    "voxel_grid_torch",
    "event_mask_torch",
    "MAX_COUNT",
    "Observation",
    "OBSERVATIONS",
    "image_input",
]


def _pixel_index(x: np.ndarray, y: np.ndarray, width: int) -> np.ndarray:
    if np.issubdtype(np.asarray(x).dtype, np.floating):
        x, y = np.rint(x), np.rint(y)
    return np.asarray(y, np.int64) * width + np.asarray(x, np.int64)


def count_image(events, sensor_size: tuple[int, int] | None = None) -> np.ndarray:
    """Event count image (paper eq. 2).

    events: an :class:`~envs.events.Events` (or anything with x, y, p arrays: x, y pixel
    coordinates, p in {-1, +1}). Returns (2, H, W) float32: [ON counts, OFF counts].
    """
    height, width = sensor_size or events.sensor_size
    idx = _pixel_index(events.x, events.y, width)
    off = np.asarray(events.p) <= 0
    counts = np.bincount(idx + off * (height * width), minlength=2 * height * width)
    return counts.reshape(2, height, width).astype(np.float32)


def event_mask(events, sensor_size: tuple[int, int] | None = None) -> np.ndarray:
    """(H, W) bool: True where the window has at least one event."""
    height, width = sensor_size or events.sensor_size
    mask = np.zeros(height * width, bool)
    mask[_pixel_index(events.x, events.y, width)] = True
    return mask.reshape(height, width)


def count_time_image(
    events, t_start: int, t_end: int, sensor_size: tuple[int, int] | None = None
) -> np.ndarray:
    """EV-FlowNet's 4-channel event image (Zhu et al., RSS 2018): (4, H, W) float32,
    [ON counts, OFF counts, ON latest time, OFF latest time].

    Channels 0-1 are :func:`count_image`. Channels 2-3 hold, per pixel and polarity, the
    normalised time ``tau = (t - t_start) / (t_end - t_start)`` of the pixel's most recent event
    (0 where it has none), divided by the largest such value in the image, so that the window's
    latest event reads 1 (as EV-FlowNet normalises its timestamp image). events: as
    :func:`count_image`, with t int64 microseconds in [t_start, t_end].
    """
    height, width = sensor_size or events.sensor_size
    n_pix = height * width
    idx = _pixel_index(events.x, events.y, width) + (np.asarray(events.p) <= 0) * n_pix
    tau = (np.asarray(events.t, np.float64) - t_start) / float(t_end - t_start)
    latest = np.zeros(2 * n_pix, np.float64)
    np.maximum.at(latest, idx, tau)
    top = latest.max(initial=0.0)
    if top > 0:
        latest /= top
    times = latest.reshape(2, height, width).astype(np.float32)
    return np.concatenate([count_image(events, (height, width)), times])


def voxel_grid(
    events, num_bins: int, t_start: int, t_end: int, sensor_size: tuple[int, int] | None = None
) -> np.ndarray:
    """Voxel grid with ``num_bins`` temporal bins: (num_bins, H, W) float32.

    Each event adds its polarity (+1/-1) to the two bins around ``tau * (num_bins - 1)``
    with linear weights, ``tau = (t - t_start) / (t_end - t_start)``.
    """
    height, width = sensor_size or events.sensor_size
    if num_bins < 1:
        raise ValueError(f"num_bins must be >= 1, got {num_bins}")
    idx = _pixel_index(events.x, events.y, width)
    pos = (np.asarray(events.t, np.float64) - t_start) / float(t_end - t_start) * (num_bins - 1)
    lower = np.clip(np.floor(pos), 0, num_bins - 1).astype(np.int64)
    frac = pos - lower
    upper = np.minimum(lower + 1, num_bins - 1)
    p = np.asarray(events.p, np.float64)
    n_pix = height * width
    grid = np.bincount(lower * n_pix + idx, weights=p * (1.0 - frac), minlength=num_bins * n_pix)
    grid += np.bincount(upper * n_pix + idx, weights=p * frac, minlength=num_bins * n_pix)
    return grid.reshape(num_bins, height, width).astype(np.float32)


#: Finite upper bound of the count and voxel boxes of the observations: far above any real per-pixel count.
MAX_COUNT = float(2**24)


@dataclass(frozen=True)
class Observation:
    """An image observation of one window's events: one place that the env's observation space and
    its arrays (envs.env), a policy's ``input_key``, the learner's input channels and the
    ``--input`` choices (agents.train_config) all read. A new image input is one entry of
    :data:`OBSERVATIONS`. (The env's ``"events"`` part, a (max_events, 4) list of points rather
    than an image, is no entry: the env builds it and its space itself.)

    channels: ``voxel_bins`` -> C, the channels of the (C, H, W) float32 image;
    low, high: its bounds, one for every channel or a tuple of one per channel;
    build: ``(events, t_start, t_end, size, voxel_bins)`` -> the image of the window
    ``[t_start, t_end)`` holding ``events`` (x, y, t, p attributes) on a ``size`` (H, W) frame."""

    name: str
    channels: Callable[[int], int]
    low: float | tuple[float, ...]
    high: float | tuple[float, ...]
    build: Callable[..., np.ndarray]

    def shape(self, size: tuple[int, int], voxel_bins: int) -> tuple[int, int, int]:
        """(C, H, W) of the image on a ``size`` (H, W) frame."""
        return (self.channels(voxel_bins), *size)

    def bounds(self, size: tuple[int, int], voxel_bins: int) -> tuple[np.ndarray, np.ndarray]:
        """The (C, H, W) float32 arrays of the lowest and highest values the image takes."""
        shape = self.shape(size, voxel_bins)
        return tuple(np.broadcast_to(np.asarray(bound, np.float32).reshape(-1, 1, 1), shape).copy()
                     for bound in (self.low, self.high))


#: The image observations by name (the env's parts, ``--input``'s choices), in the env's order.
OBSERVATIONS: dict[str, Observation] = {obs.name: obs for obs in (
    Observation("count_image", channels=lambda bins: 2, low=0.0, high=MAX_COUNT,
                build=lambda events, t_start, t_end, size, bins: count_image(events, size)),
    Observation("voxel_grid", channels=lambda bins: bins, low=-MAX_COUNT, high=MAX_COUNT,
                build=lambda events, t_start, t_end, size, bins: voxel_grid(events, bins, t_start, t_end, size)),
    Observation("count_time_image", channels=lambda bins: 4, low=0.0, high=(MAX_COUNT, MAX_COUNT, 1.0, 1.0),
                build=lambda events, t_start, t_end, size, bins: count_time_image(events, t_start, t_end, size)),
)}


def image_input(kind: str, events, t_start: int, t_end: int, size: tuple[int, int], voxel_bins: int = 5) -> np.ndarray:
    """The network input ``kind`` (one of :data:`OBSERVATIONS`) of the window ``[t_start, t_end)``
    holding ``events`` (an :class:`~envs.events.Events`, ``window.events``), on an ``size`` (H, W) frame."""
    if kind not in OBSERVATIONS:
        raise ValueError(f"no image input named {kind!r}; one of {tuple(OBSERVATIONS)}")
    return OBSERVATIONS[kind].build(events, t_start, t_end, size, voxel_bins)


# --- torch, batched -------------------------------------------------------------------------


def _torch_pixel_index(x: torch.Tensor, y: torch.Tensor, width: int) -> torch.Tensor:
    if x.is_floating_point():
        x, y = torch.round(x), torch.round(y)
    return y.long() * width + x.long()


def count_image_torch(
    x: torch.Tensor, y: torch.Tensor, p: torch.Tensor, mask: torch.Tensor | None, sensor_size: tuple[int, int]
) -> torch.Tensor:
    """Batched count images: x, y, p (B, N) (p in {-1,+1}), mask (B, N) bool for padded
    batches. Returns (B, 2, H, W) float32, equal to :func:`count_image` per element."""
    height, width = sensor_size
    batch = x.shape[0]
    n_pix = height * width
    idx = _torch_pixel_index(x, y, width) + (p <= 0).long() * n_pix
    idx = idx + torch.arange(batch, device=x.device).unsqueeze(1) * (2 * n_pix)
    weights = torch.ones_like(idx, dtype=torch.float64) if mask is None else mask.to(torch.float64)
    out = torch.zeros(batch * 2 * n_pix, dtype=torch.float64, device=x.device)
    out.index_add_(0, idx.reshape(-1), weights.reshape(-1))
    return out.reshape(batch, 2, height, width).to(torch.float32)


def event_mask_torch(
    x: torch.Tensor, y: torch.Tensor, mask: torch.Tensor | None, sensor_size: tuple[int, int]
) -> torch.Tensor:
    """Batched event masks: (B, H, W) bool."""
    ones = torch.ones_like(x, dtype=torch.float64)
    counts = count_image_torch(x, y, ones, mask, sensor_size)
    return counts[:, 0] > 0


def voxel_grid_torch(
    x: torch.Tensor,
    y: torch.Tensor,
    tau: torch.Tensor,
    p: torch.Tensor,
    mask: torch.Tensor | None,
    num_bins: int,
    sensor_size: tuple[int, int],
) -> torch.Tensor:
    """Batched voxel grids: tau (B, N) normalised time in [0, 1); returns (B, num_bins, H, W)
    float32, equal to :func:`voxel_grid` per element when tau is computed in float64."""
    height, width = sensor_size
    batch = x.shape[0]
    n_pix = height * width
    idx = _torch_pixel_index(x, y, width)
    pos = tau.to(torch.float64) * (num_bins - 1)
    lower = torch.clamp(torch.floor(pos), 0, num_bins - 1).long()
    frac = pos - lower
    upper = torch.clamp(lower + 1, max=num_bins - 1)
    weight = p.to(torch.float64) * (1.0 if mask is None else mask.to(torch.float64))
    base = torch.arange(batch, device=x.device).unsqueeze(1) * (num_bins * n_pix)
    out = torch.zeros(batch * num_bins * n_pix, dtype=torch.float64, device=x.device)
    out.index_add_(0, (base + lower * n_pix + idx).reshape(-1), (weight * (1 - frac)).reshape(-1))
    out.index_add_(0, (base + upper * n_pix + idx).reshape(-1), (weight * frac).reshape(-1))
    return out.reshape(batch, num_bins, height, width).to(torch.float32)
