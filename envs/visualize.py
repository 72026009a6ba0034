"""Pictures of event windows and flow fields (uint8 RGB, H x W x 3).

- :func:`flow_to_rgb`: the standard optical-flow colour wheel (Baker et al., Middlebury):
  hue = direction, saturation = magnitude relative to ``max_magnitude``; zero flow is white.
- :func:`count_image_to_rgb`: ON events red, OFF events blue, on white.
- :func:`save_png`: writes a picture atomically (Pillow, the ``plots``/``test`` extra).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

__all__ = ["color_wheel", "flow_to_rgb", "count_image_to_rgb", "save_png"]

# Hue segments of the Middlebury wheel: red-yellow, yellow-green, green-cyan, cyan-blue,
# blue-magenta, magenta-red, with these many steps each.
_SEGMENTS = (15, 6, 4, 11, 13, 6)


def color_wheel() -> np.ndarray:
    """(55, 3) float64 RGB in [0, 255]: the wheel's colours in order of angle."""
    ramps = []
    # (channel that is full, channel that ramps, ramp up or down) for each segment
    plan = ((0, 1, +1), (1, 0, -1), (1, 2, +1), (2, 1, -1), (2, 0, +1), (0, 2, -1))
    for steps, (full, moving, direction) in zip(_SEGMENTS, plan):
        seg = np.zeros((steps, 3))
        seg[:, full] = 255
        ramp = np.floor(255 * np.arange(steps) / steps)
        seg[:, moving] = ramp if direction > 0 else 255 - ramp
        ramps.append(seg)
    return np.concatenate(ramps)


def flow_to_rgb(flow: np.ndarray, max_magnitude: float | None = None) -> np.ndarray:
    """Colour-code a flow field.

    flow: (2, H, W) pixels (x then y). max_magnitude: the magnitude shown fully saturated
    (default: the field's largest finite magnitude). Returns (H, W, 3) uint8.
    """
    flow = np.asarray(flow, np.float64)
    if flow.ndim != 3 or flow.shape[0] != 2:
        raise ValueError(f"flow must be (2, H, W), got {flow.shape}")
    u, v = np.nan_to_num(flow[0]), np.nan_to_num(flow[1])
    magnitude = np.hypot(u, v)
    if max_magnitude is None:
        max_magnitude = float(magnitude.max())
    scale = max(float(max_magnitude), 1e-9)
    wheel = color_wheel()
    n = len(wheel)
    angle = np.arctan2(-v, -u) / np.pi  # in [-1, 1]
    position = (angle + 1) / 2 * (n - 1)
    k0 = np.floor(position).astype(int)
    k1 = (k0 + 1) % n
    frac = (position - k0)[..., None]
    colour = (1 - frac) * wheel[k0] + frac * wheel[k1]  # (H, W, 3) in [0, 255]
    radius = np.clip(magnitude / scale, 0, 1)[..., None]
    rgb = 255 - radius * (255 - colour)
    return np.clip(np.rint(rgb), 0, 255).astype(np.uint8)


def count_image_to_rgb(count_image: np.ndarray) -> np.ndarray:
    """(2, H, W) counts [ON, OFF] -> (H, W, 3) uint8: ON red, OFF blue, no events white."""
    count_image = np.asarray(count_image, np.float64)
    if count_image.ndim != 3 or count_image.shape[0] != 2:
        raise ValueError(f"count image must be (2, H, W), got {count_image.shape}")
    scale = max(np.percentile(count_image[count_image > 0], 99) if (count_image > 0).any() else 1.0, 1.0)
    on, off = np.clip(count_image / scale, 0, 1)
    rgb = np.stack([1 - off, 1 - on - off, 1 - on], axis=-1)
    return (np.clip(rgb, 0, 1) * 255).astype(np.uint8)


def save_png(path: str | os.PathLike, rgb: np.ndarray) -> Path:
    """Write an (H, W, 3) uint8 picture as PNG through a temporary file."""
    from PIL import Image

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f"{path.name}.tmp-{os.getpid()}")
    try:
        Image.fromarray(np.ascontiguousarray(rgb)).save(tmp, format="PNG")
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
    return path
