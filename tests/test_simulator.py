"""The synthetic simulator (envs.simulator) and its named splits (envs.synthetic).

The ground truth is checked against independent oracles written here: the translation itself,
a small numpy warp-and-splat of the events (motion compensation must sharpen), and the frames
(photometric agreement after warping).
"""

from __future__ import annotations

import json
import runpy
from pathlib import Path

import numpy as np
import pytest

from envs.events import Events
from envs.simulator import AffineMotion, EventEmulator, Scene, SceneConfig, SensorConfig, simulate
from envs.synthetic import SPLITS, SyntheticH5Reader, clear_cache, get_spec, list_sequences, load_sequence

SCRIPTS = Path(__file__).resolve().parents[1] / "scripts"


@pytest.fixture(scope="module")
def moving_scene():
    """A 64x64 scene with camera pan/roll/zoom and 3 occluding objects, ~4 px per 30 Hz frame."""
    config = SceneConfig.random(7, 64, 64, speed_px_s=150.0, num_objects=3, noise=False)
    return simulate(config, duration_s=0.3)


# --- ground truth ---------------------------------------------------------------------------


def test_pure_translation_flow_equals_the_translation():
    velocity = (100.0, -200.0)  # px/s
    config = SceneConfig.translation(3, 24, 40, velocity)
    scene = Scene(config)
    for t0, t1 in ((0.0, 0.03), (0.05, 0.051), (0.2, 0.1)):
        flow = scene.flow(t0, t1)
        assert flow.shape == (2, 24, 40) and flow.dtype == np.float32
        np.testing.assert_allclose(flow[0], velocity[0] * (t1 - t0), atol=1e-4)
        np.testing.assert_allclose(flow[1], velocity[1] * (t1 - t0), atol=1e-4)
    # and the rendered image really moves that way: over 30 ms, 3 px right and 6 px up
    before, after = scene.render(0.0), scene.render(0.03)
    np.testing.assert_allclose(after[:-6, 3:], before[6:, :-3], atol=1e-4)


def test_roll_and_zoom_flow_matches_closed_form_and_the_renders():
    h, w = 48, 64
    centre = np.array([(w - 1) / 2, (h - 1) / 2])
    camera = AffineMotion(anchor=tuple(centre), angular_velocity=1.5, zoom_amp=0.2, zoom_freq=1.0, camera=True)
    scene = Scene(SceneConfig(0, h, w, camera))
    t0, t1 = 0.1, 0.15
    flow = scene.flow(t0, t1)
    # closed form: p1 = c + (s1 / s0) R(theta1 - theta0) (p - c)
    ratio = np.exp(0.2 * (np.sin(2 * np.pi * t1) - np.sin(2 * np.pi * t0)))
    angle = 1.5 * (t1 - t0)
    ys, xs = np.mgrid[0:h, 0:w].astype(float)
    dx, dy = xs - centre[0], ys - centre[1]
    x1 = centre[0] + ratio * (np.cos(angle) * dx - np.sin(angle) * dy)
    y1 = centre[1] + ratio * (np.sin(angle) * dx + np.cos(angle) * dy)
    np.testing.assert_allclose(flow[0], x1 - xs, atol=1e-4)
    np.testing.assert_allclose(flow[1], y1 - ys, atol=1e-4)
    assert np.abs(flow).max() > 3  # a real motion
    # the render at t1, sampled where the flow says, reproduces the render at t0
    inside = (x1 >= 0) & (x1 < w - 1) & (y1 >= 0) & (y1 < h - 1)
    before, after = scene.render(t0), scene.render(t1)
    error = np.abs(_bilinear(after, x1[inside], y1[inside]) - before[inside]).mean()
    assert error < 0.1 * np.abs(after - before)[inside].mean()


def _iwe_variance(events: Events, flow: np.ndarray, t0: int, t1: int) -> float:
    """Variance of the image of warped events at t1: x' = x + (1 - tau) u(x, y), nearest splat."""
    h, w = events.sensor_size
    tau = (events.t - t0) / (t1 - t0)
    x = events.x + (1 - tau) * flow[0, events.y, events.x]
    y = events.y + (1 - tau) * flow[1, events.y, events.x]
    xi, yi = np.rint(x).astype(int), np.rint(y).astype(int)
    inside = (xi >= 0) & (xi < w) & (yi >= 0) & (yi < h)
    image = np.zeros((h, w))
    np.add.at(image, (yi[inside], xi[inside]), 1.0)
    return float(image.var())


def test_warping_events_with_ground_truth_sharpens_them(moving_scene):
    seq = moving_scene
    times = seq.frame_times
    for k in range(len(times) - 1):
        t0, t1 = int(times[k]), int(times[k + 1])
        flow, valid = seq.flow_between(t0, t1)
        assert valid.all()
        assert np.abs(flow).max() > 1.0  # the check is meaningful only with real motion
        events = seq.events.slice_time(t0, t1)
        sharp = _iwe_variance(events, flow, t0, t1)
        assert sharp > 1.2 * _iwe_variance(events, 0 * flow, t0, t1)
        assert sharp > 1.2 * _iwe_variance(events, 2 * flow, t0, t1)


def _bilinear(image: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    x0, y0 = np.floor(x).astype(int), np.floor(y).astype(int)
    fx, fy = x - x0, y - y0
    im = image.astype(np.float64)
    top = im[y0, x0] * (1 - fx) + im[y0, x0 + 1] * fx
    bottom = im[y0 + 1, x0] * (1 - fx) + im[y0 + 1, x0 + 1] * fx
    return top * (1 - fy) + bottom * fy


@pytest.mark.parametrize("step", [1, 4])
def test_frames_agree_after_warping_by_ground_truth(moving_scene, step):
    seq = moving_scene
    h, w = seq.sensor_size
    ys, xs = np.mgrid[0:h, 0:w]
    errors, zero_errors = [], []
    for k in range(0, len(seq.frame_times) - step, step):
        t0, t1 = int(seq.frame_times[k]), int(seq.frame_times[k + step])
        flow, _ = seq.flow_between(t0, t1)
        x1, y1 = xs + flow[0], ys + flow[1]
        inside = (x1 >= 1) & (x1 < w - 2) & (y1 >= 1) & (y1 < h - 2)
        # unoccluded: same layer at both ends, and no layer boundary within 2 px (edge ramps)
        ids0 = seq.visible_layers(t0)
        ids1 = seq.visible_layers(t1)
        same = np.zeros_like(inside)
        same[inside] = ids1[np.rint(y1[inside]).astype(int), np.rint(x1[inside]).astype(int)] == ids0[inside]
        pad = np.pad(ids0, 2, mode="edge")
        interior = np.all([pad[2 + dy : 2 + dy + h, 2 + dx : 2 + dx + w] == ids0 for dy in range(-2, 3) for dx in range(-2, 3)], axis=0)
        keep = inside & same & interior
        assert keep.mean() > 0.3
        warped = _bilinear(seq.frames[k + step], x1[keep], y1[keep])
        errors.append(np.abs(warped - seq.frames[k][keep]))
        zero_errors.append(np.abs(seq.frames[k + step][keep].astype(float) - seq.frames[k][keep]))
    error, zero_error = np.concatenate(errors).mean(), np.concatenate(zero_errors).mean()
    assert error < 2.5  # grey levels; uint8 rounding + bilinear resampling of a smooth texture
    assert error < 0.2 * zero_error


# --- the event camera model ----------------------------------------------------------------


def test_emulator_fires_one_event_per_threshold_with_interpolated_times():
    sensor = SensorConfig(contrast_threshold=0.25, threshold_sigma=0.0, refractory_us=0)
    start = np.zeros((1, 3), np.float32)
    emulator = EventEmulator(start, sensor, np.random.default_rng(0))
    end = np.array([[1.0, -0.6, 0.1]], np.float32)  # +4 thresholds, -2 thresholds, none
    x, y, t, p = emulator.step(start, end, 1000, 2000)
    assert list(zip(x.tolist(), p.tolist())) == [(0, 1), (1, -1), (0, 1), (0, 1), (1, -1), (0, 1)]
    assert np.all(np.diff(t) >= 0) and np.all(y == 0)
    on_times = t[p > 0]
    np.testing.assert_array_equal(on_times, [1250, 1500, 1750, 1999])  # the 4th crossing is at t_b
    np.testing.assert_array_equal(t[p < 0], [1416, 1833])  # 0.25/0.6 and 0.5/0.6 of the step
    np.testing.assert_allclose(emulator.ref, [1.0, -0.5, 0.0])  # the references moved with them
    # refractory period: crossings 250 us apart, 400 us refractory -> every other one fires
    emulator = EventEmulator(start, SensorConfig(threshold_sigma=0.0, refractory_us=400), np.random.default_rng(0))
    _, _, t, p = emulator.step(start, end, 1000, 2000)
    np.testing.assert_array_equal(t[p > 0], [1250, 1750])
    np.testing.assert_array_equal(t[p < 0], [1416, 1833])  # 417 us apart: both fire
    np.testing.assert_allclose(emulator.ref, [1.0, -0.5, 0.0])  # the reference still moved on


def test_noise_and_hot_pixels():
    sensor = SensorConfig(noise_rate_hz=5.0, hot_pixels=2, hot_pixel_rate_hz=2000.0)
    image = np.zeros((20, 30), np.float32)
    emulator = EventEmulator(image, sensor, np.random.default_rng(1))
    x, y, t, p = emulator.step(image, image, 0, 100_000)  # 0.1 s, no intensity change
    pixels = y.astype(int) * 30 + x
    hot = np.isin(pixels, emulator.hot_index)
    assert 150 < (~hot).sum() < 450  # 600 px * 5 Hz * 0.1 s = 300 expected
    assert 300 < hot.sum() < 500  # 2 * 2000 Hz * 0.1 s = 400 expected
    assert np.all(np.diff(t) >= 0) and set(np.unique(p)) == {-1, 1}


def test_events_are_valid_and_substeps_small(moving_scene):
    seq = moving_scene
    ev = seq.events
    assert len(ev) > 1000
    checked = Events.create(ev.x, ev.y, ev.t, ev.p, seq.sensor_size)  # raises on any violation
    assert checked.x.dtype == np.int16 and checked.t.dtype == np.int64 and checked.p.dtype == np.int8
    assert ev.t[0] >= 0 and ev.t[-1] < seq.duration_us
    assert (ev.p == 1).sum() > 0.2 * len(ev) and (ev.p == -1).sum() > 0.2 * len(ev)
    # 300 px/s over 0.2 s = 60 px of travel at <= 0.25 px per sub-step
    fast = simulate(SceneConfig.translation(0, 16, 16, (300.0, 0.0)), duration_s=0.2)
    assert fast.num_substeps >= 240


def test_same_seed_same_events_and_frames():
    config = SceneConfig.random(11, 32, 48, speed_px_s=120.0)
    a, b = simulate(config, 0.15), simulate(SceneConfig.random(11, 32, 48, speed_px_s=120.0), 0.15)
    for field in "xytp":
        np.testing.assert_array_equal(getattr(a.events, field), getattr(b.events, field))
    np.testing.assert_array_equal(a.frames, b.frames)
    c = simulate(SceneConfig.random(12, 32, 48, speed_px_s=120.0), 0.15)
    assert len(c.events) != len(a.events) or not np.array_equal(c.events.x, a.events.x)


def test_config_round_trips_through_json():
    config = SceneConfig.random(5, 40, 60)
    back = SceneConfig.from_dict(json.loads(json.dumps(config.to_dict())))
    assert back == config


def test_reader_and_frames(moving_scene):
    seq = moving_scene
    reader = seq.reader("demo")
    assert reader.sensor_size == (64, 64) and reader.num_events == len(seq.events)
    np.testing.assert_array_equal(reader.flow_timestamps(), seq.frame_times)
    np.testing.assert_array_equal(seq.frame_times, [0, 33333, 66667, 100000, 133333, 166667, 200000, 233333, 266667, 300000])
    assert seq.frames.shape == (10, 64, 64) and seq.frames.dtype == np.uint8
    assert reader.frame(3).std() > 10  # textured
    flow, valid = reader.flow_between(1000, 21000)
    assert flow.shape == (2, 64, 64) and valid.dtype == bool


# --- splits ----------------------------------------------------------------------------------


def test_split_catalogue():
    assert {"synthetic-train", "synthetic-test", "synthetic-mini"} <= set(SPLITS)
    train, test = list_sequences("synthetic-train"), list_sequences("synthetic-test")
    assert len(train) == 32 and {(s.height, s.width) for s in train} == {(128, 128)}
    assert {(s.height, s.width) for s in test} == {(128, 128), (256, 256)}
    names = [s.name for split in SPLITS.values() for s in split]
    # every split its own scenes, but synthetic-train-soft and -sparse: synthetic-train's scenes,
    # weaker textured / with larger leaves
    twins = ("synthetic-train-soft", "synthetic-train-sparse", "synthetic-train-wide")
    seeds = [s.seed for name, split in SPLITS.items() if name not in twins for s in split]
    assert len(set(names)) == len(names) and len(set(seeds)) == len(seeds)
    for twin in twins:
        assert [s.seed for s in SPLITS[twin]] == [s.seed for s in train]
    motion = [s.max_flow_px for s in train]
    assert min(motion) <= 0.5 and max(motion) >= 10
    assert get_spec("synthetic-test", "synthetic-test-256-01") is test[9]
    with pytest.raises(ValueError, match="synthetic-train"):
        list_sequences("synthetic-validation")


def test_load_sequence_caches_in_memory_and_on_disk(tmp_path, monkeypatch):
    monkeypatch.setenv("EVFLOW_CACHE", str(tmp_path))
    clear_cache()
    try:
        reader = load_sequence("synthetic-mini", 1)  # simulates and writes the cache file
        (path,) = tmp_path.glob("synthetic/synthetic-mini/synthetic-mini-1-*.h5")
        stamp = path.stat().st_mtime_ns
        again = load_sequence("synthetic-mini", "synthetic-mini-1")  # in-process hit: same file
        reader.close()  # a caller closing its reader does not break the cache
        assert again.num_events == reader.num_events and len(again.events_range(0, 10)) == 10
        again.close()
        clear_cache()
        cached = load_sequence("synthetic-mini", 1)  # now from the file on disk
        assert isinstance(cached, SyntheticH5Reader) and path.stat().st_mtime_ns == stamp
        exact = get_spec("synthetic-mini", 1).simulate()
        events = cached.events_range(0, cached.num_events)
        for field in "xytp":
            np.testing.assert_array_equal(getattr(events, field), getattr(exact.events, field))
        grid = cached.flow_timestamps()
        np.testing.assert_array_equal(grid, exact.frame_times)
        for a, b in ((grid[3], grid[4]), (grid[2], grid[6]), (12345, 23456)):  # stored, dt=4, any
            np.testing.assert_allclose(cached.flow_between(int(a), int(b))[0], exact.flow_between(int(a), int(b))[0], atol=1e-5)
        np.testing.assert_array_equal(cached.frame(5), exact.frames[5])
        cached.close()
        in_memory = load_sequence("synthetic-mini", 1, disk_cache=False)
        assert not isinstance(in_memory, SyntheticH5Reader) and in_memory.num_events == len(exact.events)
        assert load_sequence("synthetic-mini", 1, disk_cache=False) is in_memory
    finally:
        clear_cache()


def test_generate_script_writes_h5_files(tmp_path):
    from envs.readers import H5Reader

    main = runpy.run_path(str(SCRIPTS / "generate_synthetic.py"))["main"]
    main(["--split", "synthetic-mini", "--out", str(tmp_path), "--num", "1", "--no-progress"])
    (path,) = tmp_path.glob("*.h5")
    with H5Reader(path) as reader:
        assert reader.name == "synthetic-mini-0" and reader.num_events > 0
        assert reader.provenance["split"] == "synthetic-mini"
        grid = reader.flow_timestamps()
        assert len(grid) == 31 and reader.flow_between(int(grid[0]), int(grid[1])) is not None
