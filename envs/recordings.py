"""Small recordings with known motion (dots translating at a constant velocity, the exact flow
known everywhere), in memory or written in the project h5 format: what the tests and the
benchmarks run on, and a quick check of a pipeline (``write_translating_recording(path, rng)``)."""

from __future__ import annotations

import numpy as np

from envs.events import Events
from envs.readers import write_h5

__all__ = ["translating_dots", "write_translating_recording"]


def translating_dots(
    rng: np.random.Generator,
    *,
    sensor_size=(48, 64),
    velocity=(200.0, -100.0),  # pixels per second (x, y)
    duration_us=300_000,
    num_dots=120,
    events_per_s=60_000,
):
    """Events of dots translating at constant velocity: each event is one dot at its current
    (rounded) position, so the exact flow over [t0, t1) is velocity * (t1 - t0) everywhere."""
    h, w = sensor_size
    n = int(events_per_s * duration_us / 1e6)
    t = np.sort(rng.integers(0, duration_us, n))
    dot = rng.integers(0, num_dots, n)
    start = rng.uniform(0, [w, h], size=(num_dots, 2))
    pos = start[dot] + np.outer(t / 1e6, velocity)
    x, y = (np.rint(pos[:, 0]) % w).astype(np.int64), (np.rint(pos[:, 1]) % h).astype(np.int64)
    p = np.where(dot % 2 == 0, 1, -1)
    return Events.create(x, y, t, p, sensor_size), (0, duration_us)


def write_translating_recording(path, rng, *, frame_us=30_000, **kwargs):
    """A project h5 file of :func:`translating_dots` with ground truth on a frame grid."""
    events, (t0, t1) = translating_dots(rng, **kwargs)
    velocity = kwargs.get("velocity", (200.0, -100.0))
    h, w = events.sensor_size
    grid = np.arange(t0, t1 + 1, frame_us)
    flows = []
    for a, b in zip(grid[:-1], grid[1:]):
        flow = np.empty((2, h, w), np.float32)
        flow[0], flow[1] = velocity[0] * (b - a) / 1e6, velocity[1] * (b - a) / 1e6
        flows.append((int(a), int(b), flow, np.ones((h, w), bool)))
    return write_h5(path, events, flows=flows, t_start_us=t0, t_end_us=t1, name=path.stem)
