"""Events held in memory as recordings (envs/memory.py): a structured array (tonic's layout), a
mapping of four arrays or Events give the env, and agents.predict_flow, exactly what the same
events written to a file give."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

import envs  # noqa: F401  (registers EventFlow-v0)
from agents import predict_flow
from envs.events import EventError
from envs.memory import events_from_memory
from envs.readers import write_h5
from tests.recordings import translating_dots

SIZE = (40, 56)


def _structured(events, t_dtype="<i8"):
    array = np.zeros(len(events), dtype=[("t", t_dtype), ("x", "<i2"), ("y", "<i2"), ("p", "?")])
    array["x"], array["y"], array["t"], array["p"] = events.x, events.y, events.t, events.p > 0
    return array


@pytest.fixture
def dots(rng):
    events, _ = translating_dots(rng, sensor_size=SIZE, duration_us=150_000)
    return events


def _observations(data, **kwargs):
    env = gym.make("EventFlow-v0", data=data, window="time", window_size=20_000, **kwargs)
    obs, info = env.reset(options={"sequence": 0})
    out = [(obs["count_image"], info["window"].t_start, info["window"].t_end)]
    for _ in range(3):
        obs, _, _, _, info = env.step(np.zeros((2, *SIZE), np.float32))
        out.append((obs["count_image"], info["window"].t_start, info["window"].t_end))
    env.close()
    return out


def test_memory_layouts_give_what_the_file_gives(tmp_path, dots):
    path = write_h5(tmp_path / "dots.h5", dots, t_start_us=int(dots.t[0]), t_end_us=int(dots.t[-1]) + 1)
    reference = _observations(str(path))
    layouts = {
        "structured": (_structured(dots), SIZE),
        "tonic size (W, H, P)": (_structured(dots), (SIZE[1], SIZE[0], 2)),
        "float t": (_structured(dots, "<f8"), SIZE),
        "mapping": ({"x": dots.x, "y": dots.y, "t": dots.t, "p": dots.p}, SIZE),
        "Events": (dots, None),
    }
    for name, (data, size) in layouts.items():
        got = _observations(data, sensor_size=size)
        for (a, ta0, ta1), (b, tb0, tb1) in zip(got, reference):
            assert (ta0, ta1) == (tb0, tb1) and np.array_equal(a, b), name


def test_bad_memory_events_are_refused_naming_the_problem(dots):
    array = _structured(dots)
    with pytest.raises(ValueError, match="need sensor_size"):
        gym.make("EventFlow-v0", data=array)
    seconds = _structured(dots, "<f8")
    seconds["t"] = seconds["t"] / 1e6
    with pytest.raises(ValueError, match="whole microseconds"):
        events_from_memory(seconds, SIZE)
    with pytest.raises(EventError, match="'x'"):
        events_from_memory(array, (SIZE[0], 10))  # x beyond a 10-pixel-wide sensor
    with pytest.raises(ValueError, match="sensor_size must be"):
        events_from_memory(array, (1, 2, 3, 4))
    with pytest.raises(TypeError, match="structured array"):
        events_from_memory(np.zeros(4), SIZE)


def test_predict_flow_on_memory_events_is_the_files_flow(tmp_path, dots):
    path = write_h5(tmp_path / "dots.h5", dots, t_start_us=int(dots.t[0]), t_end_us=int(dots.t[-1]) + 1)
    flows, bounds = predict_flow(_structured(dots), sensor_size=SIZE, max_windows=3)
    from_file, file_bounds = predict_flow(str(path), max_windows=3)
    assert flows.shape == (3, 2, *SIZE) and flows.dtype == np.float32
    assert np.array_equal(bounds, file_bounds) and np.array_equal(flows, from_file)
    assert bounds[0, 0] == dots.t[0] and np.all(np.diff(bounds, axis=1) == 33_333)
    alone, _ = predict_flow(_structured(dots), sensor_size=SIZE, max_windows=3, finish=False)
    assert not np.array_equal(alone, flows)  # the default's finish moved the proposal


@pytest.mark.parametrize("suffix", [".npy", ".npz"])
def test_convert_to_numpy_and_back_keeps_every_event(tmp_path, dots, suffix):
    from envs.readers import open_recording
    from envs.readers.base import FormatError
    from evflow_cli.commands.convert import main as convert

    path = write_h5(tmp_path / "dots.h5", dots, t_start_us=int(dots.t[0]), t_end_us=int(dots.t[-1]) + 1)
    out = tmp_path / f"dots{suffix}"
    assert convert([str(path), str(out), "--chunk-events", "1000"]) == 0  # several chunks
    if suffix == ".npy":  # a bare array stores no geometry: named on reading
        with pytest.raises(FormatError, match="stores no sensor size"):
            open_recording(out)
    again = open_recording(out, sensor_size=SIZE) if suffix == ".npy" else open_recording(out)
    assert again.sensor_size == SIZE
    got = again.events_range(0, again.num_events)
    for field in ("x", "y", "t"):
        assert np.array_equal(getattr(got, field), getattr(dots, field))
    assert np.array_equal(got.p > 0, dots.p > 0)
    assert [p.name for p in tmp_path.iterdir()] and not list(tmp_path.glob("*.tmp-*"))


def test_a_pickled_numpy_file_runs_nothing(tmp_path):
    from envs.readers import open_recording
    from envs.readers.base import FormatError

    marker = tmp_path / "pwned"

    class Evil:
        def __reduce__(self):
            import os
            return os.system, (f"touch {marker}",)

    np.save(tmp_path / "evil.npy", np.array([Evil()], dtype=object), allow_pickle=True)
    with pytest.raises(FormatError, match="not a readable numpy file"):
        open_recording(tmp_path / "evil.npy", sensor_size=SIZE)
    assert not marker.exists()
