"""tools/density_speed.py: per window, the mean speed from the ground truth and the events per pixel
per frame, on a recording whose motion is known."""

import numpy as np
import pytest

from envs.env import EventFlowEnv
from tests.conftest import load_script
from tests.recordings import write_translating_recording


@pytest.fixture(scope="module")
def density_speed():
    return load_script("tools/density_speed.py")


@pytest.mark.parametrize("dt", [1, 2])
def test_speed_and_density_of_a_known_translation(density_speed, tmp_path, dt):
    path = write_translating_recording(tmp_path / "dots.h5", np.random.default_rng(2), sensor_size=(24, 32))
    rows = density_speed.from_ground_truth(str(path), dt)
    # 200 and -100 px/s over 30 ms frames: (6, -3) px per frame, whatever the window's length
    np.testing.assert_allclose(rows[:, 0], np.hypot(6.0, -3.0), rtol=1e-5)
    env = EventFlowEnv(str(path), window="frames", window_size=dt, compute_reward=False)
    _, info = env.reset(options={"sequence": 0})
    counts, firing, truncated = [], [], False
    while not truncated:
        window = info["window"]
        counts.append(len(window.events.t))
        firing.append(len({(int(x), int(y)) for x, y in zip(window.events.x, window.events.y)}) / (24 * 32))
        _, _, _, truncated, info = env.step(np.zeros(env.action_space.shape, np.float32))
    np.testing.assert_allclose(rows[:, 1], np.array(counts) / (24 * 32 * dt))
    np.testing.assert_allclose(rows[:, 2], firing)
    assert 0 < rows[:, 2].min() and rows[:, 2].max() < 1
    lines = density_speed.table("dots", rows, dt)
    # every window in one bin, with the median share of firing pixels and events per firing pixel
    per_firing = np.median(np.array(counts) / (24 * 32 * np.array(firing)))
    assert any(line.startswith(f"| [4,8) | {len(rows)} |") and line.endswith(f" | {per_firing:.2f} |") for line in lines)


def test_a_target_file_of_the_ground_truth_gives_the_ground_truths_rows(density_speed, tmp_path):
    """--targets reads a training split's teacher targets like the ground truth: a target file whose
    grids are the ground truth's flow gives its windows' event densities, and as the speed the
    mean over every cell (the flow the reader puts on pixels without valid ground truth included)."""
    from envs.readers import H5Reader
    from tests.test_teacher import _write_ground_truth_targets

    path = str(write_translating_recording(tmp_path / "dots.h5", np.random.default_rng(4), sensor_size=(24, 32)))
    targets = _write_ground_truth_targets(tmp_path / "targets.h5", path, sizes=(1, 2))
    with H5Reader(path) as reader:
        stamps = np.asarray(reader.flow_timestamps(), np.int64)
        for dt in (1, 2):
            spans = list(zip(stamps[::dt][:-1], stamps[::dt][1:]))
            speeds = [np.linalg.norm(reader.flow_between(int(a), int(b))[0], axis=0).mean() / dt for a, b in spans]
            rows = density_speed.from_targets(str(targets), dt)
            np.testing.assert_allclose(rows[:, 0], speeds, rtol=1e-5)
            np.testing.assert_allclose(rows[:, 1:], density_speed.from_ground_truth(path, dt)[:, 1:])
