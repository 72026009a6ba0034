"""tonic's events and datasets wherever a recording goes (the ``tonic`` extra): a dataset written
as tonic's own datasets are (a ``tonic.dataset.Dataset`` whose samples are ``(events, target)``
with tonic's structured dtype, a transform applied), one recording per sample."""

from __future__ import annotations

import numpy as np
import pytest

tonic = pytest.importorskip("tonic")

from agents.evaluation import evaluate  # noqa: E402
from envs.env import EventFlowEnv  # noqa: E402

SIZE = (40, 48)  # height, width


def _translating(seed: int, n: int = 30_000, speed: float = 40.0) -> np.ndarray:
    """Events drifting right at ``speed`` px/s over 0.3 s, in tonic's dtype."""
    rng = np.random.default_rng(seed)
    t = np.sort(rng.integers(0, 300_000, n))
    x0 = rng.integers(0, SIZE[1] // 2, n)
    x = np.clip(x0 + speed * t / 1e6, 0, SIZE[1] - 1).astype(np.int16)
    y = rng.integers(0, SIZE[0], n).astype(np.int16)
    return tonic.io.make_structured_array(x, y, t, rng.integers(0, 2, n).astype(bool), dtype=tonic.io.events_struct)


class Moving(tonic.dataset.Dataset):
    """Three recordings, as tonic's datasets hold them (sensor_size is width, height, polarities)."""

    sensor_size = (SIZE[1], SIZE[0], 2)
    dtype = tonic.io.events_struct
    ordering = dtype.names

    def __init__(self, transform=None):
        super().__init__(save_to=".", transform=transform)
        self.samples = [_translating(seed) for seed in range(3)]

    def __getitem__(self, index):
        events = self.samples[index]
        return (self.transform(events) if self.transform else events), index

    def __len__(self):
        return len(self.samples)


def test_a_tonic_dataset_is_one_recording_per_sample_as_its_arrays_are():
    dataset = Moving()
    env = EventFlowEnv(dataset, window="time", window_size=20_000, compute_reward=True)
    assert env.sequence_names == ["Moving-0", "Moving-1", "Moving-2"] and (env.height, env.width) == SIZE
    alone = EventFlowEnv(dataset.samples[1], sensor_size=dataset.sensor_size, window="time", window_size=20_000)
    obs, info = env.reset(options={"sequence": 1})
    obs_alone, info_alone = alone.reset()
    np.testing.assert_array_equal(obs["count_image"], obs_alone["count_image"])
    flow = np.zeros((2, *SIZE), np.float32)
    flow[0] = 40.0 * 0.02  # the dots' motion over a 20 ms window
    (_, reward, *_), (_, reward_alone, *_) = env.step(flow), alone.step(flow)
    assert reward == reward_alone and np.isfinite(reward)  # the same window, scored the same


def test_tonic_transforms_apply_before_the_env_reads_the_events():
    dropped = Moving(transform=tonic.transforms.DropEvent(p=0.5))
    results = evaluate(None, dropped, window="time", window_size=50_000, progress=False, measures=())
    whole = evaluate(None, Moving(), window="time", window_size=50_000, progress=False, measures=())
    assert [r.name for r in results] == ["Moving-0", "Moving-1", "Moving-2"]
    assert all(r.windows == w.windows == 6 for r, w in zip(results, whole))
    env = EventFlowEnv(dropped, window="time", window_size=250_000)
    _, info = env.reset()
    assert 0.4 * 25_000 < len(info["window"].events) < 0.6 * 25_000  # about half dropped by tonic's transform


def test_an_empty_dataset_or_a_wrong_size_is_refused_in_one_line():
    empty = Moving()
    empty.samples = []
    with pytest.raises(ValueError, match="the dataset Moving holds no samples"):
        EventFlowEnv(empty)
    wrong = Moving()
    wrong.sensor_size = (10, 10, 2)  # smaller than the events' coordinates
    with pytest.raises(ValueError, match=r"data Moving-0: field 'x' must lie in \[0, 10\) for sensor 10x10"):
        EventFlowEnv(wrong, window="time", window_size=20_000).reset()
