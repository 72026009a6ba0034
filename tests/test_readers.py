"""Readers for real recordings: each test writes a small file exactly as the public layout
describes (docs/formats.md) and reads it back through the reader and ``open_recording``."""

from __future__ import annotations

import sys
import types

import h5py
import numpy as np
import pytest

from envs.env import EventFlowEnv
from envs.events import Events
from envs.readers import FormatError, H5Reader, open_recording
from envs.readers.dsec import DSECReader, decode_flow_png, encode_flow_png
from envs.readers.hagenaars import HagenaarsReader
from envs.readers.mvsec import MVSECReader, mvsec_eval_windows
from envs.readers.png16 import read_png, write_png
from envs.readers.text import TextReader
from envs.windows import iter_windows

EPOCH_US = 1_504_645_177_123_456  # an MVSEC-like epoch time, µs


def _stream(rng, n, sensor_size, span_us):
    h, w = sensor_size
    t = np.sort(rng.integers(0, span_us, n))
    t[n // 2 : n // 2 + 5] = t[n // 2]  # repeated timestamps
    return rng.integers(0, w, n), rng.integers(0, h, n), t.astype(np.int64), rng.integers(0, 2, n)


def _assert_events(ev: Events, x, y, t, p01):
    np.testing.assert_array_equal(ev.x, x)
    np.testing.assert_array_equal(ev.y, y)
    np.testing.assert_array_equal(ev.t, t)
    np.testing.assert_array_equal(ev.p, np.where(np.asarray(p01) > 0, 1, -1))
    assert ev.t.dtype == np.int64 and ev.p.dtype == np.int8


def _check_index(reader, t, rng):
    for q in np.concatenate([rng.integers(int(t[0]) - 5, int(t[-1]) + 5, 60), [t[0], t[-1], t[len(t) // 2]]]):
        assert reader.index_at(int(q)) == np.searchsorted(t, q), q


# ---------------------------------------------------------------------------------------- MVSEC
def write_mvsec(folder, name, x, y, t_us, p01, *, images=None, image_t_us=None, gt=None, compressed=False):
    """MVSEC: davis/left/events (N, 4) float64 [x, y, epoch seconds, p in {-1,+1}];
    image_raw (F, 260, 346) uint8 + image_raw_ts; gt npz timestamps + x/y_flow_dist (K, 260, 346)."""
    path = folder / f"{name}_data.hdf5"
    with h5py.File(path, "w") as f:
        ev = np.stack([x, y, (EPOCH_US + t_us) / 1e6, np.where(p01 > 0, 1.0, -1.0)], axis=1).astype(np.float64)
        f.create_dataset("davis/left/events", data=ev, chunks=(min(4096, len(x)), 4), compression="gzip")
        if images is not None:
            f.create_dataset("davis/left/image_raw", data=images)
            f.create_dataset("davis/left/image_raw_ts", data=(EPOCH_US + image_t_us) / 1e6)
    if gt is not None:
        gt_t_us, fx, fy = gt
        save = np.savez_compressed if compressed else np.savez
        save(folder / f"{name}_gt_flow_dist.npz", timestamps=(EPOCH_US + gt_t_us) / 1e6, x_flow_dist=fx, y_flow_dist=fy)
    return path


@pytest.fixture
def mvsec_file(tmp_path, rng):
    x, y, t, p = _stream(rng, 20_000, (260, 346), 400_000)
    images = rng.integers(0, 256, (5, 260, 346), dtype=np.uint8)
    image_t = np.array([1_000, 51_000, 101_000, 151_000, 201_000])
    gt_t = np.arange(6) * 50_000  # 20 Hz
    fx = np.zeros((6, 260, 346))
    fy = np.zeros((6, 260, 346))
    fx[:] = 2.0  # constant translation of (2, -1) px per 50 ms interval
    fy[:] = -1.0
    path = write_mvsec(tmp_path, "indoor_flying1", x, y, t - t[0], p, images=images, image_t_us=image_t, gt=(gt_t, fx, fy))
    return path, (x, y, t - t[0], p), images, image_t, gt_t


def test_mvsec_events_frames_and_times_to_the_microsecond(mvsec_file, rng):
    path, (x, y, t, p), images, image_t, _ = mvsec_file
    with MVSECReader(path) as r:
        assert r.sensor_size == (260, 346) and r.num_events == len(t) and r.name == "indoor_flying1"
        assert r.origin_us == EPOCH_US and (r.t_start, r.t_end) == (0, int(t[-1]) + 1)
        _assert_events(r.events_range(0, r.num_events), x, y, t, p)
        _check_index(r, t, rng)
        windows = list(iter_windows(r, "time", 10_000))
        assert sum(len(w.events) for w in windows) == len(t)
        np.testing.assert_array_equal(r.frame_timestamps(), image_t)
        np.testing.assert_array_equal(r.frame(3), images[3])
        np.testing.assert_array_equal(r.flow_timestamps(), image_t)  # the EV-FlowNet grid: images


def test_mvsec_crop_center256_shifts_events_and_crops_gt_and_frames(mvsec_file):
    path, (x, y, t, p), images, _, gt_t = mvsec_file
    with MVSECReader(path, crop="center256") as r:
        assert r.crop == (2, 45, 256, 256) and r.sensor_size == (256, 256)
        keep = (x >= 45) & (x < 301) & (y >= 2) & (y < 258)
        _assert_events(r.events_range(0, r.num_events), x[keep] - 45, y[keep] - 2, t[keep], p[keep])
        np.testing.assert_array_equal(r.frame(1), images[1, 2:258, 45:301])
        flow, valid = r.flow_between(int(gt_t[0]), int(gt_t[1]))
        assert flow.shape == (2, 256, 256) and valid.all()
        np.testing.assert_allclose(flow[:, 0, 0], [2.0, -1.0])
    with pytest.raises(ValueError, match="does not fit"):
        MVSECReader(path, crop=(250, 0, 20, 20))


def test_mvsec_ground_truth_dt1_dt4_scaling_and_propagation(mvsec_file):
    path, _, _, _, gt_t = mvsec_file
    with MVSECReader(path, grid="gt") as r:
        np.testing.assert_array_equal(r.flow_timestamps(), gt_t)
        flow, valid = r.flow_between(0, 50_000)  # dt = 1: the stored map
        assert valid.all() and np.allclose(flow[0], 2.0) and np.allclose(flow[1], -1.0)
        flow, valid = r.flow_between(10_000, 35_000)  # inside one interval: half the map
        assert np.allclose(flow[0], 1.0) and np.allclose(flow[1], -0.5) and valid.all()
        flow, valid = r.flow_between(0, 200_000)  # dt = 4: propagated through 4 maps
        assert np.allclose(flow[0][valid], 8.0) and np.allclose(flow[1][valid], -4.0)
        # a pixel is valid only while its path stays on the sensor: x + 2k <= 345, y - k >= 0
        # at each of the 4 lookups (k = 0..3)
        ys, xs = np.mgrid[0:260, 0:346]
        np.testing.assert_array_equal(valid, (xs + 6 <= 345) & (ys - 3 >= 0))
        assert (flow[:, ~valid] == 0).all()
        assert r.flow_between(0, 260_000) is None  # past the last map
        frames4 = list(iter_windows(r, "frames", 4))
        assert [(w.t_start, w.t_end) for w in frames4] == [(0, 200_000)]


def test_mvsec_compressed_npz_streams_the_same_gt(tmp_path, rng):
    gt_t = np.arange(4) * 50_000
    fx = rng.normal(size=(4, 260, 346))
    fy = rng.normal(size=(4, 260, 346))
    x, y, t, p = _stream(rng, 500, (260, 346), 150_000)
    t = t - t[0]  # the reader's time origin is the first event
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    a = write_mvsec(tmp_path / "a", "outdoor_day1", x, y, t, p, gt=(gt_t, fx, fy))
    b = write_mvsec(tmp_path / "b", "outdoor_day1", x, y, t, p, gt=(gt_t, fx, fy), compressed=True)
    with MVSECReader(a) as ra, MVSECReader(b) as rb:
        assert ra._gt_x._mmap is not None and rb._gt_x._mmap is None  # stored: memmap, deflated: stream
        for t0, t1 in [(50_000, 100_000), (0, 50_000), (60_000, 150_000), (0, 150_000)]:
            fa, va = ra.flow_between(t0, t1)
            fb, vb = rb.flow_between(t0, t1)
            np.testing.assert_array_equal(fa, fb)
            np.testing.assert_array_equal(va, vb)
        flow, _ = ra.flow_between(50_000, 100_000)
        np.testing.assert_allclose(flow, np.stack([fx[1], fy[1]]).astype(np.float32))


def test_mvsec_protocol_windows():
    grid = np.arange(0, 5000) * 50_000  # 20 Hz for 250 s
    stub = types.SimpleNamespace(flow_timestamps=lambda: grid, name="x", sequence="indoor_flying1")
    w1 = mvsec_eval_windows(stub, 1)
    assert (w1[0] == [grid[60], grid[61]]).all() and w1[-1][1] == grid[1340] and len(w1) == 1280
    w4 = mvsec_eval_windows(stub, 4)
    assert (w4[0] == [grid[60], grid[64]]).all() and len(w4) == 320
    out = mvsec_eval_windows(stub, 1, "outdoor_day1")
    assert out[0][0] == 222_400_000 and out[-1][1] == 240_400_000 and len(out) == 360
    out = mvsec_eval_windows(stub, 1, "outdoor_day1", outdoor_cut="frames")
    assert out[0][0] == grid[4356] and out[-1][1] == grid[4706]


def test_mvsec_wrong_layout_names_the_dataset(tmp_path):
    path = tmp_path / "bad_data.hdf5"
    with h5py.File(path, "w") as f:
        f.create_dataset("davis/left/image_raw", data=np.zeros((1, 260, 346), np.uint8))
    with pytest.raises(FormatError, match="/davis/left/events"):
        MVSECReader(path)
    with h5py.File(path, "w") as f:
        f.create_dataset("davis/left/events", data=np.zeros((5, 3)))
    with pytest.raises(FormatError, match=r"/davis/left/events.*\(N, 4\)"):
        MVSECReader(path)
    with h5py.File(path, "w") as f:
        f.create_dataset("davis/left/events", data=np.zeros((5, 4)))
    np.savez(tmp_path / "gt.npz", timestamps=np.arange(3.0), y_flow_dist=np.zeros((3, 260, 346)))
    with pytest.raises(FormatError, match="missing array 'x_flow_dist'"):
        MVSECReader(path, gt=tmp_path / "gt.npz")
    np.savez(tmp_path / "gt.npz", timestamps=np.arange(3.0), x_flow_dist=np.zeros((3, 26, 34)), y_flow_dist=np.zeros((3, 26, 34)))
    with pytest.raises(FormatError, match=r"'x_flow_dist' has shape \(3, 26, 34\)"):
        MVSECReader(path, gt=tmp_path / "gt.npz")


# ------------------------------------------------------------------------------------ Hagenaars
def write_hagenaars(path, x, y, t_us, p01, *, t0_s=1.5e3, flows=(), images=(), ps_bool=True, hqf=False):
    """events/xs, ys int16; ts float64 seconds; ps bool; attrs t0, duration, sensor_resolution (H, W);
    flows: (group, end_us, (2,H,W)[, start_us]); images: (t_us, (H,W) uint8); timestamps in seconds
    like ts; a flow with start_us also gets the start attribute ``timestamp_from``."""
    with h5py.File(path, "w") as f:
        f.create_dataset("events/xs", data=x.astype(np.int16), chunks=True, compression="gzip")
        f.create_dataset("events/ys", data=y.astype(np.int16), chunks=True, compression="gzip")
        f.create_dataset("events/ts", data=t0_s + t_us / 1e6, chunks=True, compression="gzip")
        f.create_dataset("events/ps", data=(p01 > 0) if ps_bool else p01.astype(np.uint8), chunks=True)
        f.attrs["t0"] = t0_s
        f.attrs["duration"] = float(t_us[-1]) / 1e6
        f.attrs["sensor_resolution"] = (20, 30)
        f.attrs["num_events"] = len(x)
        for k, (group, end_us, flow, *start) in enumerate(flows):
            ds = f.create_dataset(f"{group}/flow{k:09d}", data=flow.astype(np.float32))
            ds.attrs["timestamp"] = t0_s + end_us / 1e6
            if start:
                ds.attrs["timestamp_from"] = t0_s + start[0] / 1e6
        for k, (t_us_img, image) in enumerate(images):
            ds = f.create_dataset(f"images/image{k:09d}", data=image)
            ds.attrs["timestamp"] = t0_s + t_us_img / 1e6
    return path


def test_hagenaars_events_flow_groups_and_frames(tmp_path, rng):
    x, y, t, p = _stream(rng, 5_000, (20, 30), 300_000)
    grid = np.arange(0, 300_001, 50_000)
    shift = np.zeros((2, 20, 30))
    shift[0], shift[1] = 1.0, 0.5
    dt1 = [("flow_dt1", int(g), shift) for g in grid]
    d4 = shift * 4
    d4[:, 0, 0] = np.nan  # invalid pixels: NaN ...
    d4[:, 1, 1] = 0.0  # ... and both components 0
    dt4 = [("flow_dt4", int(grid[4]), d4)]
    images = [(int(g), rng.integers(0, 256, (20, 30), dtype=np.uint8)) for g in grid[:3]]
    path = write_hagenaars(tmp_path / "seq.h5", x, y, t, p, flows=dt1 + dt4, images=images)
    with open_recording(path) as r:
        assert isinstance(r, HagenaarsReader) and r.sensor_size == (20, 30)
        _assert_events(r.events_range(0, r.num_events), x, y, t, p)
        _check_index(r, t, rng)
        np.testing.assert_array_equal(r.flow_timestamps(), grid)
        flow, valid = r.flow_between(50_000, 100_000)  # map k ends at grid[k]: spans [grid[k-1], grid[k])
        assert valid.all() and np.allclose(flow[0], 1.0) and np.allclose(flow[1], 0.5)
        flow, valid = r.flow_between(0, 200_000)  # the stored dt4 map
        assert not valid[0, 0] and not valid[1, 1] and valid.sum() == 20 * 30 - 2
        assert np.allclose(flow[0][valid], 4.0) and flow[0, 0, 0] == 0
        flow, valid = r.flow_between(50_000, 250_000)  # not stored: chained dt1 maps
        assert np.allclose(flow[0][valid], 4.0) and np.allclose(flow[1][valid], 2.0)
        np.testing.assert_array_equal(r.frame(2), images[2][1])
        np.testing.assert_array_equal(r.frame_timestamps(), grid[:3])


def test_hagenaars_hqf_flow_group_uint8_polarity_and_start_convention(tmp_path, rng):
    x, y, t, p = _stream(rng, 1_000, (20, 30), 100_000)
    maps = [rng.normal(size=(2, 20, 30)) for _ in range(3)]
    flows = [("flow", 0, maps[0]), ("flow", 40_000, maps[1]), ("flow", 80_000, maps[2])]
    path = write_hagenaars(tmp_path / "hqf.h5", x, y, t, p, flows=flows, ps_bool=False, t0_s=0.25)
    with HagenaarsReader(path) as r:
        _assert_events(r.events_range(0, r.num_events), x, y, t, p)
        np.testing.assert_allclose(r.flow_between(0, 40_000)[0], maps[1].astype(np.float32))
    with HagenaarsReader(path, flow_timestamp="start") as r:
        np.testing.assert_allclose(r.flow_between(0, 40_000)[0], maps[0].astype(np.float32))


def test_hagenaars_start_attributes_deliver_the_first_window(tmp_path, rng):
    """Maps that state their start: the first map is used, and a GT-aligned episode delivers
    every event from the first start to the last end exactly once."""
    x, y, t, p = _stream(rng, 4_000, (20, 30), 300_000)
    starts = np.arange(20_000, 260_001, 60_000)
    maps = [np.full((2, 20, 30), k + 1.0) for k in range(len(starts))]
    flows = [("flow_dt1", int(a + 60_000), m, int(a)) for a, m in zip(starts, maps)]
    path = write_hagenaars(tmp_path / "stated.h5", x, y, t, p, flows=flows)
    with HagenaarsReader(path) as r:
        np.testing.assert_array_equal(r.flow_timestamps(), np.append(starts, starts[-1] + 60_000))
        np.testing.assert_allclose(r.flow_between(20_000, 80_000)[0], maps[0])  # the first map
        chained, valid = r.flow_between(20_000, 140_000)  # chained: 1 px, then 2 px from where it landed
        assert valid[:-1, :-1].all() and np.allclose(chained[:, valid], 3.0)
    env = EventFlowEnv(str(path), window="frames", compute_reward=False)
    _, info = env.reset(options={"sequence": 0})
    seen, gts, truncated = [], [], False
    while not truncated:
        seen.append(np.asarray(info["window"].events.t))
        gts.append(float(info["flow_gt"][0, 0, 0]))
        _, _, _, truncated, info = env.step(np.zeros((2, 20, 30), np.float32))
    inside = t[(t >= starts[0]) & (t < starts[-1] + 60_000)]
    np.testing.assert_array_equal(np.concatenate(seen), inside)
    assert gts == [k + 1.0 for k in range(len(starts))]


def test_hagenaars_wrong_layout_names_the_dataset(tmp_path, rng):
    path = tmp_path / "bad.h5"
    with h5py.File(path, "w") as f:
        for k in ("xs", "ys", "ps"):
            f.create_dataset(f"events/{k}", data=np.zeros(3, np.int16))
        f.attrs["sensor_resolution"] = (2, 2)
    with pytest.raises(FormatError, match="/events/ts"):
        HagenaarsReader(path)
    with h5py.File(path, "a") as f:
        f.create_dataset("events/ts", data=np.zeros(3))
        del f.attrs["sensor_resolution"]
    with pytest.raises(FormatError, match="sensor_resolution"):
        HagenaarsReader(path)


# ----------------------------------------------------------------------------------------- DSEC
T_OFFSET = 1_234_567_890_123


def write_dsec(folder, x, y, t_rel, p01, *, compression=True):
    """events/x,y uint16; t uint32 µs relative; p uint8; ms_to_idx uint64; t_offset int64;
    Blosc/zstd through hdf5plugin (as DSEC ships it)."""
    import hdf5plugin

    folder.mkdir(parents=True, exist_ok=True)
    path = folder / "events.h5"
    comp = dict(hdf5plugin.Blosc(cname="zstd", clevel=1, shuffle=hdf5plugin.Blosc.SHUFFLE)) if compression else {}
    with h5py.File(path, "w") as f:
        for name, data, dtype in (("x", x, np.uint16), ("y", y, np.uint16), ("t", t_rel, np.uint32), ("p", p01, np.uint8)):
            f.create_dataset(f"events/{name}", data=data.astype(dtype), chunks=True, **comp)
        ms = np.searchsorted(t_rel, 1000 * np.arange(int(t_rel[-1]) // 1000 + 1), side="left")
        f.create_dataset("ms_to_idx", data=ms.astype(np.uint64))
        f.create_dataset("t_offset", data=np.int64(T_OFFSET))
    return path


def test_dsec_events_index_and_absolute_times(tmp_path, rng):
    x, y, t, p = _stream(rng, 30_000, (480, 640), 250_000)
    t[5000:5300] = t[5000]  # a burst spanning ms boundaries' lookups
    t = np.sort(t)
    path = write_dsec(tmp_path / "zurich_city_01_a" / "events" / "left", x, y, t, p)
    with open_recording(tmp_path / "zurich_city_01_a" / "events" / "left") as r:  # a folder works
        assert isinstance(r, DSECReader) and r.sensor_size == (480, 640) and not r.rectified
        assert r.name == "zurich_city_01_a" and r.t_start == T_OFFSET
        _assert_events(r.events_range(0, r.num_events), x, y, t + T_OFFSET, p)
        _check_index(r, t + T_OFFSET, rng)
        w = list(iter_windows(r, "time", 10_000))
        assert sum(len(v.events) for v in w) == len(t)
    with pytest.raises(FormatError, match="t_offset"):
        with h5py.File(path, "a") as f:
            del f["t_offset"]
        DSECReader(path)


def test_dsec_rectification_and_flow_pngs(tmp_path, rng):
    x, y, t, p = _stream(rng, 2_000, (480, 640), 300_000)
    folder = tmp_path / "seq"
    path = write_dsec(folder, x, y, t, p)
    rect = np.zeros((480, 640, 2), np.float32)
    ys, xs = np.mgrid[0:480, 0:640]
    rect[..., 0], rect[..., 1] = xs + 0.25, ys - 0.5  # row 0 maps off the sensor
    with h5py.File(folder / "rectify_map.h5", "w") as f:
        f.create_dataset("rectify_map", data=rect)
    flow_dir = tmp_path / "flow" / "forward"
    flow_dir.mkdir(parents=True)
    maps = []
    for k in range(2):
        flow = np.round(rng.normal(0, 20, (2, 480, 640)) * 128) / 128  # 1/128 px resolution
        valid = rng.random((480, 640)) > 0.2
        encode_flow_png(flow_dir / f"{2 * k + 2:06d}.png", flow, valid, filters=[0, 1, 2, 3, 4] * 96)
        maps.append((np.where(valid, flow, 0), valid))
    (tmp_path / "flow" / "forward_timestamps.txt").write_text(
        "# from_timestamp_us, to_timestamp_us\n"
        f"{T_OFFSET + 0}, {T_OFFSET + 100_000}\n{T_OFFSET + 100_000}, {T_OFFSET + 200_000}\n"
    )
    with DSECReader(path, flow_dir=flow_dir) as r:
        assert r.rectified  # rectify_map.h5 beside events.h5
        ev = r.events_range(0, r.num_events)
        keep = (y >= 1) & (x + 0.25 <= 639)
        np.testing.assert_array_equal(ev.x, (x[keep] + 0.25).astype(np.float32))
        np.testing.assert_array_equal(ev.y, (y[keep] - 0.5).astype(np.float32))
        np.testing.assert_array_equal(ev.t, t[keep] + T_OFFSET)
        np.testing.assert_array_equal(r.flow_timestamps(), T_OFFSET + np.array([0, 100_000, 200_000]))
        flow, valid = r.flow_between(T_OFFSET + 100_000, T_OFFSET + 200_000)
        np.testing.assert_array_equal(valid, maps[1][1])
        np.testing.assert_array_equal(flow, maps[1][0].astype(np.float32))
        half, _ = r.flow_between(T_OFFSET + 25_000, T_OFFSET + 75_000)
        np.testing.assert_allclose(half, maps[0][0] * 0.5, atol=1e-6)
        assert r.flow_between(T_OFFSET + 50_000, T_OFFSET + 150_000) is None
    with DSECReader(path, rectify=False) as r:
        assert r.events_range(0, 10).x.dtype == np.int16


def test_dsec_of_another_sensor_size_takes_it_from_its_files(tmp_path, rng):
    """A 346x260 recording in the DSEC layout: the size comes from the rectify map and the flow
    PNGs; files that disagree, or events outside the stated size, are refused by name."""
    x, y, t, p = _stream(rng, 3_000, (260, 346), 200_000)
    folder = tmp_path / "davis"
    write_dsec(folder, x, y, t, p)
    ys, xs = np.mgrid[0:260, 0:346].astype(np.float32)
    with h5py.File(folder / "rectify_map.h5", "w") as f:
        f.create_dataset("rectify_map", data=np.stack([xs, ys], axis=-1))
    flow_dir = tmp_path / "flow"
    flow_dir.mkdir()
    flow = np.round(rng.normal(0, 3, (2, 260, 346)) * 128) / 128
    encode_flow_png(flow_dir / "000002.png", flow, np.ones((260, 346), bool))
    (flow_dir / "timestamps.txt").write_text(f"# from_us, to_us\n{T_OFFSET + 50_000}, {T_OFFSET + 150_000}\n")
    with DSECReader(folder / "events.h5", flow_dir=flow_dir) as r:
        assert r.sensor_size == (260, 346) and r.rectified
        _assert_events(r.events_range(0, r.num_events), x, y, t + T_OFFSET, p)
        got, valid = r.flow_between(T_OFFSET + 50_000, T_OFFSET + 150_000)
        assert valid.all() and np.allclose(got, flow, atol=1 / 256)
    env = EventFlowEnv(str(folder), data_options={"flow_dir": str(flow_dir)})
    obs, info = env.reset(options={"sequence": 0})
    assert obs["count_image"].shape == (2, 260, 346) and info["windowing"] == "ground truth"
    encode_flow_png(flow_dir / "000002.png", flow[:, :200], np.ones((200, 346), bool))
    with pytest.raises(FormatError, match=r"disagree.*260x346.*200x346"):
        DSECReader(folder / "events.h5", flow_dir=flow_dir)
    with pytest.raises(FormatError, match=r"outside the 300x200 sensor"):
        DSECReader(folder / "events.h5", rectify=False, sensor_size=(200, 300))


def test_dsec_without_hdf5plugin_says_install_the_extra(tmp_path, rng, monkeypatch):
    x, y, t, p = _stream(rng, 100, (480, 640), 5_000)
    path = write_dsec(tmp_path / "d", x, y, t, p)
    plain = write_dsec(tmp_path / "plain", x, y, t, p, compression=False)
    monkeypatch.setitem(sys.modules, "hdf5plugin", None)  # import hdf5plugin -> ImportError
    with pytest.raises(ImportError, match=r"pip install evflow-gym\[dsec\]"):
        DSECReader(path)
    with DSECReader(plain) as r:  # gzip-free, plugin-free files still read
        assert r.num_events == 100


def test_png16_codec_reads_every_filter_and_pillow_8bit(tmp_path, rng):
    from PIL import Image

    for channels in (1, 3, 4):
        for dtype in (np.uint8, np.uint16):
            image = rng.integers(0, np.iinfo(dtype).max + 1, (9, 13, channels)).astype(dtype).squeeze()
            write_png(tmp_path / "a.png", image, filters=list(rng.integers(0, 5, 9)))
            np.testing.assert_array_equal(read_png(tmp_path / "a.png"), image)
    image = rng.integers(0, 256, (31, 17, 3), dtype=np.uint8)
    Image.fromarray(image).save(tmp_path / "b.png", optimize=True)  # libpng's adaptive filters
    np.testing.assert_array_equal(read_png(tmp_path / "b.png"), image)
    flow = np.array([[[1.5, -2.0078125]], [[0.0, 255.9921875]]])
    encode_flow_png(tmp_path / "f.png", flow, np.array([[True, True]]))
    raw = read_png(tmp_path / "f.png")
    assert raw[0, 0].tolist() == [2**15 + 192, 2**15, 1]  # x = (R - 2^15) / 128, y = (G - 2^15) / 128
    np.testing.assert_array_equal(decode_flow_png(tmp_path / "f.png")[0], flow.astype(np.float32))


# ----------------------------------------------------------------------------------------- text
def write_ecd(folder, x, y, t_us, p01, *, header=None, images=()):
    """ECD events.txt: 't x y p' lines, t in seconds (9 decimals), p 0/1; images.txt 't path'."""
    folder.mkdir(parents=True, exist_ok=True)
    lines = [header] if header else []
    lines += [f"{ti / 1e6:.9f} {xi} {yi} {pi}" for ti, xi, yi, pi in zip(t_us, x, y, p01)]
    (folder / "events.txt").write_text("\n".join(lines) + "\n")
    if images:
        from PIL import Image

        (folder / "images").mkdir()
        rows = []
        for k, (ti, image) in enumerate(images):
            Image.fromarray(image).save(folder / "images" / f"frame_{k:08d}.png")
            rows.append(f"{ti / 1e6:.6f} images/frame_{k:08d}.png")
        (folder / "images.txt").write_text("\n".join(rows) + "\n")
    return folder / "events.txt"


def test_ecd_text_streams_blocks_and_frames(tmp_path, rng):
    x, y, t, p = _stream(rng, 3_000, (180, 240), 2_000_000)
    t[100:140] = t[100]  # equal timestamps across a block boundary (block_lines=32)
    t = np.sort(t) + 12_345_678
    images = [(int(t[0]), rng.integers(0, 256, (180, 240), dtype=np.uint8)), (int(t[-1]), rng.integers(0, 256, (180, 240), dtype=np.uint8))]
    path = write_ecd(tmp_path / "shapes_rotation", x, y, t, p, images=images)
    with TextReader(path, block_lines=32) as r:
        assert r.sensor_size == (180, 240) and r.num_events == 3_000 and r.name == "shapes_rotation"
        _assert_events(r.events_range(0, r.num_events), x, y, t, p)
        _assert_events(r.events_range(95, 170), x[95:170], y[95:170], t[95:170], p[95:170])
        _check_index(r, t, rng)
        assert r.time_of(1234) == t[1234] and (r.t_start, r.t_end) == (t[0], t[-1] + 1)
        np.testing.assert_array_equal(r.frame(1), images[1][1])
        np.testing.assert_array_equal(r.frame_timestamps(), [t[0], t[-1]])
        assert len(r._cache) <= 2  # only the last two parsed blocks are kept
    with open_recording(tmp_path / "shapes_rotation", block_lines=64) as r:
        assert isinstance(r, TextReader) and r.num_events == 3000


def test_text_header_size_and_malformed_lines(tmp_path, rng):
    x, y, t, p = _stream(rng, 50, (300, 400), 10_000)
    path = write_ecd(tmp_path / "a", x, y, t, p, header="400 300")
    with open_recording(path) as r:
        assert r.sensor_size == (300, 400)
        _assert_events(r.events_range(0, 50), x, y, t, p)
    bad = tmp_path / "bad.txt"
    bad.write_text("0.1 1 2 1\n0.2 1 2\n")
    with pytest.raises(FormatError, match="t x y p|columns"):
        TextReader(bad)
    bad.write_text("0.2 1 2 1\n0.1 1 2 1\n")
    with pytest.raises(FormatError, match="'t' decreases at event 1"):
        TextReader(bad)


# ---------------------------------------------------------------------------------------- AEDAT4
def test_aedat_missing_package_says_install_the_extra(tmp_path, monkeypatch):
    path = tmp_path / "rec.aedat4"
    path.write_bytes(b"#!AER-DAT4.0\r\n")
    monkeypatch.setitem(sys.modules, "aedat", None)
    with pytest.raises(ImportError, match=r"install the 'aedat' extra: pip install evflow-gym\[aedat\]"):
        open_recording(path)


class _FakeDecoder:
    """The documented aedat 2.x Decoder API: id_to_stream() and an iterator of packets."""

    packets: list = []

    def __init__(self, path):
        self.path = path

    def id_to_stream(self):
        return {0: {"type": "events", "width": 30, "height": 20}, 1: {"type": "frame", "width": 30, "height": 20},
                2: {"type": "imus"}}

    def __iter__(self):
        return iter(self.packets)


def test_aedat_reader_adapts_the_decoder_packets(tmp_path, rng, monkeypatch):
    dtype = [("t", "<u8"), ("x", "<u2"), ("y", "<u2"), ("on", "?")]
    x, y, t, p = _stream(rng, 900, (20, 30), 50_000)
    t = t + 1_700_000_000_000_000
    chunks = [np.zeros(n, dtype) for n in (300, 0, 600)]
    for c, sl in zip(chunks, (slice(0, 300), slice(300, 300), slice(300, 900))):
        c["t"], c["x"], c["y"], c["on"] = t[sl], x[sl], y[sl], p[sl] > 0
    gray = rng.integers(0, 256, (20, 30), dtype=np.uint8)
    rgb16 = rng.integers(0, 65536, (10, 12, 3), dtype=np.uint16)
    _FakeDecoder.packets = [
        {"stream_id": 0, "events": chunks[0]},
        {"stream_id": 1, "frame": {"t": int(t[0]), "format": "L", "width": 30, "height": 20, "offset_x": 0, "offset_y": 0, "pixels": gray}},
        {"stream_id": 2, "imus": np.zeros(3)},
        {"stream_id": 0, "events": chunks[1]},
        {"stream_id": 0, "events": chunks[2]},
        {"stream_id": 1, "frame": {"t": int(t[-1]), "format": "RGB", "width": 12, "height": 10, "offset_x": 5, "offset_y": 4, "pixels": rgb16}},
    ]
    monkeypatch.setitem(sys.modules, "aedat", types.SimpleNamespace(Decoder=_FakeDecoder))
    path = tmp_path / "rec.aedat4"
    path.write_bytes(b"#!AER-DAT4.0\r\n")
    r = open_recording(path, cache_dir=tmp_path)
    assert r.sensor_size == (20, 30) and r.num_events == 900
    _assert_events(r.events_range(0, 900), x, y, t, p)
    np.testing.assert_array_equal(r.frame(0), gray)
    expected = np.zeros((20, 30), np.uint8)
    expected[4:14, 5:17] = np.rint((rgb16 >> 8).astype(np.float32).mean(axis=2))
    np.testing.assert_array_equal(r.frame(1), expected)
    cache = r._cache_path
    assert cache.exists()
    r.close()
    assert not cache.exists()


def test_aedat_real_decoder(tmp_path):
    """The reader's first packet equals what the real decoder gives, on a recording of your own
    (EVFLOW_AEDAT4_SAMPLE=path) or else on an AEDAT 4.0 file written by tests/aedat4_writer.py."""
    aedat = pytest.importorskip("aedat")  # in the test extra: CI runs this
    import os

    from tests.aedat4_writer import Stream, event_packet, write_aedat4

    sample = os.environ.get("EVFLOW_AEDAT4_SAMPLE")
    if not sample:
        rng = np.random.default_rng(5)
        t = np.sort(rng.integers(1_000_000, 1_020_000, 600)).astype(np.int64)
        x, y = rng.integers(0, 30, 600), rng.integers(0, 20, 600)
        on = rng.random(600) < 0.5
        packets = [(0, event_packet(t[a:b], x[a:b], y[a:b], on[a:b])) for a, b in ((0, 250), (250, 600))]
        sample = write_aedat4(tmp_path / "sample.aedat4", {0: Stream("EVTS", 30, 20)}, packets)
    first = next(p["events"] for p in aedat.Decoder(str(sample)) if "events" in p)
    with open_recording(sample, cache_dir=tmp_path) as r:
        ev = r.events_range(0, len(first))
        np.testing.assert_array_equal(ev.t, first["t"].astype(np.int64))
        np.testing.assert_array_equal(ev.p > 0, first["on"])


# ------------------------------------------------------------------------------ detection, misc
def test_open_recording_detects_and_names_formats(tmp_path, mvsec_file, rng):
    path = mvsec_file[0]
    with open_recording(path) as r:
        assert isinstance(r, MVSECReader) and r.has_flow
    with open_recording(path, "mvsec", crop="center256") as r:
        assert r.sensor_size == (256, 256)
    with open_recording(path.parent) as r:  # folder with one *_data.hdf5
        assert isinstance(r, MVSECReader)
    with pytest.raises(FormatError, match="ground truth"):
        open_recording(path.with_name("indoor_flying1_gt_flow_dist.npz"))
    other = tmp_path / "other.h5"
    with h5py.File(other, "w") as f:
        f.create_dataset("stuff", data=[1])
    with pytest.raises(FormatError, match="unknown layout"):
        open_recording(other)
    with pytest.raises(ValueError, match="unknown format"):
        open_recording(path, "mp4")
    from envs.readers import write_h5

    own = write_h5(tmp_path / "own.h5", Events.create([1], [2], [3], [1], (4, 5)))
    with open_recording(own) as r:
        assert isinstance(r, H5Reader)


def test_streaming_reads_stay_window_sized(tmp_path, rng):
    """Searching and windowing never read the whole time column (bounded memory)."""
    x, y, t, p = _stream(rng, 200_000, (20, 30), 20_000_000)
    path = write_hagenaars(tmp_path / "big.h5", x, y, t, p)
    with HagenaarsReader(path) as r:
        reads = []
        inner = r._times._read
        r._times._read = lambda i0, i1: reads.append(i1 - i0) or inner(i0, i1)
        sizes = [len(w.events) for w in iter_windows(r, "time", 100_000)]
        assert sum(sizes) == len(t)
        assert max(reads) <= r._times.block < len(t) // 4
        assert len(reads) < 2 * len(sizes) + 64  # a probe or a block per window, not more


def test_convert_to_project_h5(tmp_path, mvsec_file):
    from envs.readers.convert import convert_recording

    path = mvsec_file[0]
    with MVSECReader(path, crop="center256", grid="gt") as src:
        out = convert_recording(src, tmp_path / "out" / "flying1.h5")
        with H5Reader(out) as dst:
            a, b = src.events_range(0, src.num_events), dst.events_range(0, dst.num_events)
            assert dst.sensor_size == (256, 256) and dst.num_events == len(a) < src.num_events
            for field in "xytp":
                np.testing.assert_array_equal(getattr(a, field), getattr(b, field))
            np.testing.assert_array_equal(dst.flow_timestamps(), src.flow_timestamps())
            for t0, t1 in zip(src.flow_timestamps()[:-1], src.flow_timestamps()[1:]):
                np.testing.assert_array_equal(dst.flow_between(t0, t1)[0], src.flow_between(t0, t1)[0])
            np.testing.assert_array_equal(dst.frame(2), src.frame(2))
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["flying1.h5"]


def test_convert_script_detects_the_format_and_writes_atomically(tmp_path, rng, capsys):
    from tests.conftest import load_script

    script = load_script("scripts/convert.py")
    x, y, t, p = _stream(rng, 3_000, (20, 30), 200_000)
    grid = np.arange(0, 200_001, 50_000)
    flows = [("flow_dt1", int(g), np.ones((2, 20, 30))) for g in grid]
    src = write_hagenaars(tmp_path / "hq.h5", x, y, t, p, flows=flows)
    out = tmp_path / "out.h5"
    assert script.main([str(src), str(out), "--chunk-events", "1000"]) == 0
    with H5Reader(out) as r:
        _assert_events(r.events_range(0, r.num_events), x, y, t, p)
        np.testing.assert_array_equal(r.flow_timestamps(), grid)  # map k spans [grid[k-1], grid[k])
        assert np.allclose(r.flow_between(50_000, 100_000)[0], 1.0)
        assert r.provenance["reader"] == "HagenaarsReader"
    (tmp_path / "broken.h5").write_bytes(b"\x89HDF\r\n\x1a\nbroken")
    with pytest.raises(FormatError):
        script.main([str(tmp_path / "broken.h5"), str(tmp_path / "never.h5")])
    assert not (tmp_path / "never.h5").exists() and not list(tmp_path.glob("never.h5.tmp-*"))


def test_convert_interrupted_leaves_no_output(tmp_path, rng):
    from envs.readers.base import ArrayReader
    from envs.readers.convert import convert_recording

    x, y, t, p = _stream(rng, 5_000, (20, 30), 100_000)

    class Failing(ArrayReader):
        def events_range(self, i_start, i_end):
            if i_start >= 2_000:
                raise OSError("disk went away")
            return super().events_range(i_start, i_end)

    reader = Failing(Events.create(x, y, t, p, (20, 30)))
    with pytest.raises(OSError, match="disk went away"):
        convert_recording(reader, tmp_path / "out.h5", chunk_events=1_000)
    assert list(tmp_path.iterdir()) == []


def test_sorted_column_search_matches_numpy(rng):
    from envs.readers._common import SortedColumn

    t = np.sort(rng.integers(0, 5_000, 20_000))
    col = SortedColumn(lambda i0, i1: t[i0:i1].copy(), len(t), block=256)
    for _ in range(2_000):
        q = int(rng.integers(-10, 5_010))
        lo = int(rng.integers(0, len(t)))
        hi = int(rng.integers(lo, len(t) + 1))
        if rng.random() < 0.5:
            lo, hi = 0, len(t)
        assert col.searchsorted(q, lo, hi) == lo + np.searchsorted(t[lo:hi], q), (q, lo, hi)
