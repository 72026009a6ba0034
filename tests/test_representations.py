import numpy as np
import torch

from envs.events import Events
from envs.representations import (
    count_image,
    count_image_torch,
    count_time_image,
    event_mask,
    event_mask_torch,
    voxel_grid,
    voxel_grid_torch,
)
from tests.conftest import random_events


def count_image_loop(events: Events) -> np.ndarray:
    image = np.zeros((2,) + events.sensor_size, np.float32)
    for x, y, p in zip(events.x, events.y, events.p):
        image[0 if p > 0 else 1, y, x] += 1
    return image


def voxel_grid_loop(events: Events, bins: int, t0: int, t1: int) -> np.ndarray:
    grid = np.zeros((bins,) + events.sensor_size, np.float64)
    for x, y, t, p in zip(events.x, events.y, events.t, events.p):
        pos = (t - t0) / (t1 - t0) * (bins - 1)
        for b in range(bins):
            grid[b, y, x] += p * max(0.0, 1.0 - abs(pos - b))
    return grid


def test_count_image_matches_loop(rng):
    ev = random_events(rng, 3000, sensor_size=(13, 17))
    image = count_image(ev)
    assert image.dtype == np.float32 and image.shape == (2, 13, 17)
    np.testing.assert_array_equal(image, count_image_loop(ev))
    assert image.sum() == len(ev)


def test_voxel_grid_matches_loop(rng):
    ev = random_events(rng, 2000, sensor_size=(9, 11), t_span=(0, 10_000))
    grid = voxel_grid(ev, 5, 0, 10_000)
    np.testing.assert_allclose(grid, voxel_grid_loop(ev, 5, 0, 10_000), rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(grid.sum(), ev.p.sum(), rtol=1e-6)


def test_event_mask(rng):
    ev = random_events(rng, 50, sensor_size=(10, 10))
    np.testing.assert_array_equal(event_mask(ev), count_image_loop(ev).sum(0) > 0)


def test_torch_versions_agree_exactly_with_padding(rng):
    sensor = (12, 15)
    windows = [random_events(rng, n, sensor_size=sensor, t_span=(0, 1000)) for n in (300, 0, 77)]
    n_max = max(len(w) for w in windows)

    def pad(a, fill=0):
        return np.concatenate([a, np.full(n_max - len(a), fill, a.dtype)])

    x = torch.tensor(np.stack([pad(w.x) for w in windows]).astype(np.int64))
    y = torch.tensor(np.stack([pad(w.y) for w in windows]).astype(np.int64))
    p = torch.tensor(np.stack([pad(w.p, 1) for w in windows]).astype(np.float32))
    tau = torch.tensor(np.stack([pad(w.t.astype(np.float64) / 1000.0) for w in windows]))
    mask = torch.tensor(np.stack([pad(np.ones(len(w), bool), False) for w in windows]))
    counts = count_image_torch(x, y, p, mask, sensor)
    masks = event_mask_torch(x, y, mask, sensor)
    grids = voxel_grid_torch(x, y, tau, p, mask, 4, sensor)
    for b, w in enumerate(windows):
        np.testing.assert_array_equal(counts[b].numpy(), count_image(w))
        np.testing.assert_array_equal(masks[b].numpy(), event_mask(w))
        np.testing.assert_array_equal(grids[b].numpy(), voxel_grid(w, 4, 0, 1000))


def count_time_image_loop(events: Events, t0: int, t1: int) -> np.ndarray:
    """Zhu et al.'s EV-FlowNet input written out: counts, then each pixel's latest event time
    per polarity, the whole time image divided by its largest value."""
    image = np.zeros((4,) + events.sensor_size, np.float64)
    for x, y, t, p in zip(events.x, events.y, events.t, events.p):
        c = 0 if p > 0 else 1
        image[c, y, x] += 1
        image[2 + c, y, x] = max(image[2 + c, y, x], (t - t0) / (t1 - t0))
    if image[2:].max() > 0:
        image[2:] /= image[2:].max()
    return image


def test_count_time_image_matches_loop(rng):
    ev = random_events(rng, 200, sensor_size=(11, 14))  # some pixels without events of a polarity
    t0, t1 = int(ev.t.min()) - 50, int(ev.t.max()) + 500  # the latest event before the window's end
    image = count_time_image(ev, t0, t1)
    assert image.dtype == np.float32 and image.shape == (4, 11, 14)
    np.testing.assert_allclose(image, count_time_image_loop(ev, t0, t1), rtol=1e-6, atol=0)
    np.testing.assert_array_equal(image[:2], count_image(ev))
    assert image[2:].max() == 1.0 and image[2:].min() == 0.0


def test_env_serves_the_count_time_image():
    from envs.env import EventFlowEnv

    env = EventFlowEnv("synthetic-mini", observations=("count_image", "count_time_image"), compute_reward=False)
    try:
        obs, info = env.reset(seed=0)
        for _ in range(2):
            assert env.observation_space["count_time_image"].contains(obs["count_time_image"])
            events = Events.create(*(info["window"][k] for k in ("x", "y", "t", "p")), (env.height, env.width))
            want = count_time_image_loop(events, info["window"].t_start, info["window"].t_end)
            np.testing.assert_allclose(obs["count_time_image"], want, rtol=1e-6)
            np.testing.assert_array_equal(obs["count_time_image"][:2], obs["count_image"])
            obs, _, _, _, info = env.step(np.zeros((2, env.height, env.width), np.float32))
    finally:
        env.close()
