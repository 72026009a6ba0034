import numpy as np
import pytest
import torch

from envs.events import Events
from envs.readers import ArrayReader, H5Reader, write_h5
from envs.windows import Window, iter_windows, window_bounds, window_grid
from losses import EventBatch
from tests.conftest import random_events


def brute_force_time_windows(t: np.ndarray, t0: int, t1: int, size: int):
    """Assign each event to a window by a plain loop: the obvious reference."""
    out, start = [], t0
    while start < t1:
        end = min(start + size, t1)
        out.append((start, end, [i for i in range(len(t)) if start <= t[i] < end]))
        start = end
    return out


def check_partition(windows, n_events):
    delivered = np.concatenate([np.arange(w.i_start, w.i_end) for w in windows]) if windows else np.zeros(0)
    np.testing.assert_array_equal(delivered, np.arange(n_events))


@pytest.mark.parametrize("size", [13, 777, 10_000, 250_000])
def test_time_windows_match_brute_force(rng, size):
    ev = random_events(rng, 800, t_span=(1000, 101_000))
    reader = ArrayReader(ev, t_range=(1000, 101_000))
    windows = list(iter_windows(reader, "time", size))
    reference = brute_force_time_windows(ev.t, 1000, 101_000, size)
    assert len(windows) == len(reference)
    for w, (t0, t1, idx) in zip(windows, reference):
        assert (w.t_start, w.t_end) == (t0, t1)
        np.testing.assert_array_equal(w.events.t, ev.t[idx])
        np.testing.assert_array_equal(w.events.x, ev.x[idx])
    check_partition(windows, len(ev))
    assert all(a.t_end == b.t_start for a, b in zip(windows, windows[1:]))


@pytest.mark.parametrize("size", [1, 100, 799, 800, 5000])
def test_count_windows_partition(rng, size):
    ev = random_events(rng, 800)
    windows = list(iter_windows(ArrayReader(ev), "count", size))
    check_partition(windows, len(ev))
    for k, w in enumerate(windows):
        np.testing.assert_array_equal(w.events.t, ev.t[k * size : (k + 1) * size])
        assert w.t_start == w.events.t[0] and w.t_end == w.events.t[-1] + 1


def test_frame_windows_follow_the_grid(rng):
    ev = random_events(rng, 1000, t_span=(0, 100_000))
    grid = np.array([5_000, 20_000, 33_000, 50_000, 61_000, 90_000])
    reader = ArrayReader(ev, t_range=(0, 100_000), flow_fn=lambda a, b: None, flow_times=grid)
    for dt in (1, 2, 4):
        windows = list(iter_windows(reader, "frames", dt))
        ts = grid[::dt]
        assert [(w.t_start, w.t_end) for w in windows] == list(zip(ts[:-1], ts[1:]))
        for w in windows:
            np.testing.assert_array_equal(w.events.t, ev.t[(ev.t >= w.t_start) & (ev.t < w.t_end)])


def test_frames_mode_falls_back_to_frame_times_then_to_a_fixed_grid(rng):
    ev = random_events(rng, 500, t_span=(0, 100_000))
    with_frames = ArrayReader(ev, t_range=(0, 100_000), frame_times=np.array([10_000, 40_000, 70_000, 95_000]))
    grid, kind = window_grid(with_frames)
    assert kind == "frames" and list(grid) == [10_000, 40_000, 70_000, 95_000]
    assert [tuple(b[:2]) for b in window_bounds(with_frames, "frames", 2)] == [(10_000, 70_000)]
    bare = ArrayReader(ev, t_range=(0, 100_000))
    grid, kind = window_grid(bare)
    assert kind == "time" and list(grid) == [0, 33_333, 66_666, 99_999, 133_332]
    bounds = window_bounds(bare, "frames", 1)
    assert bounds[0, 2] == 0 and bounds[-1, 3] == len(ev)  # every event in one window
    assert list(window_bounds(bare, "frames", 4)[:, :2].ravel()) == [0, 133_332]
    gt = ArrayReader(ev, t_range=(0, 100_000), flow_fn=lambda a, b: None, flow_times=np.array([0, 50_000]),
                     frame_times=np.array([0, 10_000, 20_000]))
    assert window_grid(gt)[1] == "ground truth"


def test_bad_mode_and_size():
    reader = ArrayReader(random_events(np.random.default_rng(0), 10))
    with pytest.raises(ValueError, match="window mode"):
        window_bounds(reader, "events", 10)
    with pytest.raises(ValueError, match="positive integer"):
        window_bounds(reader, "time", 0)


def test_h5_windows_equal_memory_windows(rng, tmp_path):
    ev = random_events(rng, 20_000, sensor_size=(26, 34), t_span=(3_000, 250_000))
    path = write_h5(tmp_path / "rec.h5", ev, t_start_us=2_500, t_end_us=250_000)
    memory = ArrayReader(ev, t_range=(2_500, 250_000))
    with H5Reader(path) as disk:
        for mode, size in (("time", 10_000), ("time", 3_333), ("count", 3000)):
            a, b = list(iter_windows(memory, mode, size)), list(iter_windows(disk, mode, size))
            assert [(w.t_start, w.t_end, w.i_start, w.i_end) for w in a] == [
                (w.t_start, w.t_end, w.i_start, w.i_end) for w in b
            ]
            for wa, wb in zip(a, b):
                np.testing.assert_array_equal(wa.events.t, wb.events.t)
                np.testing.assert_array_equal(wa.events.p, wb.events.p)


def test_a_window_is_the_window_dict_and_gives_the_losses_batch(rng):
    ev = random_events(rng, 500, sensor_size=(20, 30), t_span=(1_000, 21_000))
    (window,) = iter_windows(ArrayReader(ev, t_range=(1_000, 21_000)), "time", 20_000)
    assert window.sensor_size == (20, 30) and window.flow_gt is None and len(window.events) == 500
    as_dict = {**ev.as_dict(), "t_start": 1_000, "t_end": 21_000}
    for key in ("x", "y", "t", "p"):
        np.testing.assert_array_equal(getattr(window.events, key), as_dict[key])
    assert (window.t_start, window.t_end) == (1_000, 21_000)
    batch, expected = window.batch(), EventBatch.from_windows([as_dict])  # the same batch as the dict gives
    for got, want in zip(batch, expected):
        torch.testing.assert_close(got, want)
    assert window == list(iter_windows(ArrayReader(ev, t_range=(1_000, 21_000)), "time", 20_000))[0]
    with pytest.raises(TypeError, match=r"a Window is not a dict: read window.events.x"):
        window["x"]  # the earlier window dict's reading says what to read instead
    with pytest.raises(TypeError, match=r"read window.t_start"):
        window["t_start"]


def _one_window(rng, n=500, size=(20, 30), t_start=1_000, t_end=101_001):
    t = np.sort(rng.integers(t_start, t_end + 1, n))
    t[:20], t[-5:] = t_start, t_end  # repeated timestamps at both edges, some stamped t_end
    ev = Events.create(rng.integers(0, size[1], n), rng.integers(0, size[0], n), t, rng.choice([-1, 1], n), size)
    return Window(3, t_start, t_end, 7, 7 + n, ev, np.ones((2, *size), np.float32), np.ones(size, bool))


def _dict_parts(window, splits):
    """The sub-windows as cut on window dicts: equal integer bounds, events by binary search."""
    t0, t1 = window.t_start, window.t_end
    bounds = [t0 + (t1 - t0) * k // splits for k in range(splits)] + [t1]
    t = window.events.t
    edges = [0, *np.searchsorted(t, bounds[1:-1], side="left").tolist(), len(t)]
    return [({k: getattr(window.events, k)[edges[k_]:edges[k_ + 1]] for k in ("x", "y", "t", "p")},
             bounds[k_], bounds[k_ + 1]) for k_ in range(splits)]


@pytest.mark.parametrize("splits", [1, 3, 4])
def test_split_cuts_as_the_window_dicts_were_cut(rng, splits):
    window = _one_window(rng)
    parts = window.split(splits)
    for part, (arrays, t0, t1) in zip(parts, _dict_parts(window, splits), strict=True):
        assert isinstance(part, Window) and (part.t_start, part.t_end) == (t0, t1)
        assert part.sensor_size == window.sensor_size and part.index == window.index
        for key, value in arrays.items():
            np.testing.assert_array_equal(getattr(part.events, key), value)
        assert (part.flow_gt is None) == (splits > 1)
    assert [p.i_start for p in parts[1:]] == [p.i_end for p in parts[:-1]]
    assert (parts[0].i_start, parts[-1].i_end) == (window.i_start, window.i_end)
    with pytest.raises(ValueError, match="splits"):
        window.split(0)


def test_cut_keeps_the_half_open_part_and_the_closing_events(rng):
    window = _one_window(rng)
    mid = window.cut(20_000, 60_000)
    assert np.all((mid.events.t >= 20_000) & (mid.events.t < 60_000)) and mid.flow_gt is None
    assert len(mid.events) == int(np.sum((window.events.t >= 20_000) & (window.events.t < 60_000)))
    assert window.cut(60_000, window.t_end).events.t[-1] == window.t_end
    assert window.cut(window.t_start, window.t_end) == window


@pytest.mark.parametrize("rounding", ["nearest", "floor"])
def test_subsample_takes_the_even_subsample_of_the_dict_code(rng, rounding):
    window = _one_window(rng, n=1000)
    assert window.subsample(1000) is window
    got = window.subsample(333, rounding=rounding)
    pick = np.linspace(0, 999, 333)
    pick = (pick.round() if rounding == "nearest" else pick).astype(np.int64)
    for key in ("x", "y", "t", "p"):
        np.testing.assert_array_equal(getattr(got.events, key), getattr(window.events, key)[pick])
    assert (got.t_start, got.t_end, got.index) == (window.t_start, window.t_end, window.index)
    with pytest.raises(ValueError, match="rounding"):
        window.subsample(10, rounding="up")


def test_bin_divides_the_pixels_and_the_sensor(rng):
    window = _one_window(rng, size=(21, 31))
    binned = window.bin(2)
    assert binned.sensor_size == (11, 16) and binned.flow_gt is None
    np.testing.assert_array_equal(binned.events.x, np.asarray(window.events.x) // 2)
    np.testing.assert_array_equal(binned.events.y, np.asarray(window.events.y) // 2)
    np.testing.assert_array_equal(binned.events.t, window.events.t)
    assert window.bin(1).events.sensor_size == window.sensor_size
    with pytest.raises(ValueError, match="factor"):
        window.bin(0)
