
import h5py
import numpy as np
import pytest

from envs.events import EventError
from envs.readers import FormatError, H5Reader, H5Writer, write_h5
from tests.conftest import random_events


def test_round_trip_is_exact(rng, tmp_path):
    ev = random_events(rng, 150_000, sensor_size=(260, 346), t_span=(10, 2_000_000))
    flow = rng.normal(size=(2, 260, 346)).astype(np.float32)
    valid = rng.random((260, 346)) > 0.3
    frame = rng.integers(0, 256, (260, 346), dtype=np.uint8)
    path = tmp_path / "rec.h5"
    with H5Writer(path, ev.sensor_size, name="demo", provenance={"seed": 3}) as w:
        w.append_events(ev[:70_000])
        w.append_events(ev[70_000:])
        w.add_flow(1000, 34_333, flow, valid)
        w.add_frame(1000, frame)
    with H5Reader(path) as r:
        assert r.sensor_size == (260, 346) and r.num_events == len(ev) and r.name == "demo"
        assert r.provenance == {"seed": 3}
        assert (r.t_start, r.t_end) == (int(ev.t[0]), int(ev.t[-1]) + 1)
        back = r.events_range(0, r.num_events)
        for field in "xytp":
            np.testing.assert_array_equal(getattr(back, field), getattr(ev, field))
            assert getattr(back, field).dtype == getattr(ev, field).dtype
        gt_flow, gt_valid = r.flow_between(1000, 34_333)
        np.testing.assert_array_equal(gt_flow, flow)
        np.testing.assert_array_equal(gt_valid, valid)
        assert r.flow_between(1000, 34_334) is None
        np.testing.assert_array_equal(r.flow_timestamps(), [1000, 34_333])
        np.testing.assert_array_equal(r.frame(0), frame)
        np.testing.assert_array_equal(r.frame_timestamps(), [1000])


def test_index_matches_searchsorted(rng, tmp_path):
    ev = random_events(rng, 30_000, t_span=(0, 5_000_000))
    path = write_h5(tmp_path / "r.h5", ev)
    with H5Reader(path) as r:
        # the ms index is what lets a window be read without touching the rest of the file
        assert len(r._ms_to_idx) == -(-(r.t_end - r.t_start) // 1000) + 1
        for t in rng.integers(-10, 5_000_100, 300):
            assert r.index_at(int(t)) == np.searchsorted(ev.t, t)
        part = r.events_between(123_456, 654_321)
        np.testing.assert_array_equal(part.t, ev.slice_time(123_456, 654_321).t)


def test_writer_leaves_nothing_on_error(rng, tmp_path):
    ev = random_events(rng, 100)
    path = tmp_path / "out.h5"
    with pytest.raises(RuntimeError):
        with H5Writer(path, ev.sensor_size) as w:
            w.append_events(ev)
            raise RuntimeError("crash mid-write")
    assert list(tmp_path.iterdir()) == []


def test_writer_keeps_old_file_on_error(rng, tmp_path):
    ev = random_events(rng, 100)
    path = write_h5(tmp_path / "out.h5", ev)
    before = path.read_bytes()
    with pytest.raises(EventError):
        with H5Writer(path, ev.sensor_size) as w:
            w.append_events(ev[50:])
            w.append_events(ev[:50])  # goes back in time
    assert path.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["out.h5"]


def test_unsorted_file_is_a_clear_error(rng, tmp_path):
    ev = random_events(rng, 1000)
    path = write_h5(tmp_path / "r.h5", ev)
    with h5py.File(path, "r+") as f:
        t = f["events/t"][:]
        t[500], t[501] = t[501] + 7, t[500]
        f["events/t"][:] = t
    with H5Reader(path) as r, pytest.raises(EventError, match=r"r\.h5.*'t' must be non-decreasing"):
        r.events_range(0, 1000)


def test_out_of_sensor_file_is_a_clear_error(rng, tmp_path):
    path = write_h5(tmp_path / "r.h5", random_events(rng, 1000, sensor_size=(20, 30)))
    with h5py.File(path, "r+") as f:
        f["events/x"][10] = 30
    with H5Reader(path) as r, pytest.raises(EventError, match=r"'x'.*index 10"):
        r.events_range(0, 1000)


def test_missing_dataset_is_named(rng, tmp_path):
    path = write_h5(tmp_path / "r.h5", random_events(rng, 100))
    with h5py.File(path, "r+") as f:
        del f["events/p"]
    with pytest.raises(FormatError, match="missing dataset '/events/p'"):
        H5Reader(path)


def test_truncated_file_is_a_clear_error(rng, tmp_path):
    path = write_h5(tmp_path / "r.h5", random_events(rng, 50_000))
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    with pytest.raises(FormatError, match="truncated or corrupt"):
        H5Reader(path)


def test_other_layout_is_named(tmp_path):
    path = tmp_path / "other.h5"
    with h5py.File(path, "w") as f:
        f.create_dataset("davis/left/events", data=np.zeros((3, 4)))
    with pytest.raises(FormatError, match="attribute 'format'"):
        H5Reader(path)


def test_bad_flow_shape_is_named(rng, tmp_path):
    ev = random_events(rng, 10, sensor_size=(4, 5))
    with pytest.raises(ValueError, match=r"flow must be \(2, 4, 5\)"):
        with H5Writer(tmp_path / "x.h5", ev.sensor_size) as w:
            w.add_flow(0, 10, np.zeros((2, 5, 4)))
    assert not (tmp_path / "x.h5").exists()
