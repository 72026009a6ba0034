"""Ground-truth flow for arbitrary windows from a sequence of displacement maps.

Datasets such as MVSEC store one displacement map per ground-truth interval:
``D_i`` (2, H, W) pixels, the motion of each pixel between ``T_i`` and ``T_{i+1}``. A window
``[t0, t1)`` that is not one of those intervals gets its flow as follows (docs/formats.md):

1. **Inside one interval** (``T_i <= t0 < t1 <= T_{i+1}``): linear scaling,
   ``flow = D_i * (t1 - t0) / (T_{i+1} - T_i)`` (constant velocity within the interval).
2. **Across intervals**: every pixel centre ``(x, y)`` is moved through time. Starting at ``t0``,
   for each interval ``i`` touched by the window the displacement is looked up at the pixel's
   *current* position by nearest neighbour (``floor(v + 0.5)``), scaled by the fraction of the
   interval that lies inside the window, and added to the position. The flow is the final
   position minus the start. This chains the maps the way the scene moved: a pixel that moved
   in interval i is looked up where it arrived for interval i+1.

Validity: a map pixel is valid when its two components are not both 0 (MVSEC and Hagenaars
convention). A propagated pixel is valid only when every lookup along its path was inside the
sensor and valid; invalid pixels get flow 0.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

__all__ = ["flow_from_displacements", "valid_of"]


def valid_of(displacement: np.ndarray) -> np.ndarray:
    """(2, H, W) map -> (H, W) bool: not both components 0 (and finite)."""
    d = np.asarray(displacement)
    return ((d[0] != 0) | (d[1] != 0)) & np.isfinite(d[0]) & np.isfinite(d[1])


def flow_from_displacements(
    get_map: Callable[[int], np.ndarray],
    times: np.ndarray,
    t0: int,
    t1: int,
    get_valid: Callable[[int], np.ndarray] | None = None,
) -> tuple[np.ndarray, np.ndarray] | None:
    """Flow over ``[t0, t1)`` from displacement maps (see the module docstring).

    get_map(i): (2, H, W) float displacement in pixels over ``[times[i], times[i+1])``.
    times: (K + 1,) int64 µs, increasing: the map boundaries.
    get_valid(i): optional (H, W) bool validity of map i (default: :func:`valid_of`).
    Returns (flow (2, H, W) float32 pixels over the window, valid (H, W) bool), or None when the
    window is empty or not covered by ``[times[0], times[-1]]``.
    """
    times = np.asarray(times, np.int64)
    t0, t1 = int(t0), int(t1)
    if len(times) < 2 or t1 <= t0 or t0 < times[0] or t1 > times[-1]:
        return None
    valid_fn = get_valid or (lambda k: valid_of(get_map(k)))
    i = int(np.searchsorted(times, t0, side="right")) - 1  # interval holding t0
    if t1 <= times[i + 1]:
        d = np.asarray(get_map(i), np.float64)
        valid = valid_fn(i)
        flow = d * ((t1 - t0) / float(times[i + 1] - times[i]))
        return np.where(valid, flow, 0.0).astype(np.float32), valid
    first = np.asarray(get_map(i))
    h, w = first.shape[1:]
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float64)
    x, y = xs.copy(), ys.copy()
    valid = np.ones((h, w), bool)
    tc = t0
    while tc < t1:
        span = float(times[i + 1] - times[i])
        seg_end = min(int(times[i + 1]), t1)
        if span > 0:
            d = np.asarray(get_map(i), np.float64)
            ok = valid_fn(i)
            xi = np.floor(x + 0.5).astype(np.int64)
            yi = np.floor(y + 0.5).astype(np.int64)
            inside = (xi >= 0) & (xi < w) & (yi >= 0) & (yi < h)
            xi, yi = np.clip(xi, 0, w - 1), np.clip(yi, 0, h - 1)
            valid &= inside & ok[yi, xi]
            frac = (seg_end - tc) / span
            x = x + frac * d[0][yi, xi]
            y = y + frac * d[1][yi, xi]
        tc = seg_end
        i += 1
    flow = np.stack([x - xs, y - ys])
    return np.where(valid, flow, 0.0).astype(np.float32), valid
