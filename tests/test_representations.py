import numpy as np
import pytest
import torch

from envs.events import Events
from envs.representations import (
    OBSERVATIONS,
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
            events = Events.create(*(getattr(info["window"].events, k) for k in ("x", "y", "t", "p")), (env.height, env.width))
            want = count_time_image_loop(events, info["window"].t_start, info["window"].t_end)
            np.testing.assert_allclose(obs["count_time_image"], want, rtol=1e-6)
            np.testing.assert_array_equal(obs["count_time_image"][:2], obs["count_image"])
            obs, _, _, _, info = env.step(np.zeros((2, env.height, env.width), np.float32))
    finally:
        env.close()


@pytest.mark.parametrize("name", list(OBSERVATIONS))
def test_every_registered_observation_is_what_the_env_serves_and_the_learner_reads(name):
    """Each entry of envs.representations.OBSERVATIONS, as declared (channels, bounds, builder),
    is the env's observation space and its arrays on real windows, the learner's input channels
    and one of --input's choices. voxel_bins 3: a count that no fixed channel count equals."""
    from agents.learner import Learner, TrainConfig
    from envs.env import EventFlowEnv
    from evflow_cli.commands import train as train_command

    observation, bins = OBSERVATIONS[name], 3
    env = EventFlowEnv("synthetic-mini", observations=(name,), voxel_bins=bins, compute_reward=False)
    try:
        space, size = env.observation_space[name], (env.height, env.width)
        low, high = observation.bounds(size, bins)
        assert space.shape == observation.shape(size, bins) == (observation.channels(bins), *size)
        assert space.dtype == np.float32 and np.array_equal(space.low, low) and np.array_equal(space.high, high)
        obs, info = env.reset(seed=0)
        for _ in range(2):
            window = info["window"]
            image = obs[name]
            assert image.shape == space.shape and image.dtype == np.float32 and np.abs(image).sum() > 0
            assert (low <= image).all() and (image <= high).all() and space.contains(image)
            np.testing.assert_array_equal(image, observation.build(window.events, window.t_start, window.t_end, size, bins))
            obs, _, _, _, info = env.step(np.zeros((2, *size), np.float32))
    finally:
        env.close()
    learner = Learner(TrainConfig(model="ev-flownet", input=name, voxel_bins=bins, width=2, data="synthetic-mini",
                                  num_envs=1, unroll=1))
    try:
        assert learner.model_config["in_channels"] == observation.channels(bins) == learner.obs[name].shape[1]
    finally:
        learner.close()
    choices = next(a.choices for a in train_command.build_parser()._actions if a.dest == "input")
    assert list(choices) == list(OBSERVATIONS)
