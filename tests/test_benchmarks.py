"""Benchmark protocols (agents/benchmarks.py): MVSEC and DSEC scored the way published numbers
are. Small files in the public layouts, written here, against references computed here."""

from __future__ import annotations

import math
import types

import numpy as np
import pytest

from agents.benchmarks import DSECProtocol, DSECSubmissionWriter, HotPixelFilter, MVSECProtocol, dsec_table
from agents.evaluation import evaluate, results_table
from envs.events import Events
from envs.readers import FormatError
from envs.readers.dsec import decode_flow_png, encode_flow_png, read_test_timestamps
from envs.readers.mvsec import MVSECReader, mvsec_eval_windows, mvsec_hood_row, mvsec_scored_span
from envs.windows import Window
from losses.metrics import dense_flow_error
from tests.test_readers import T_OFFSET, write_dsec, write_mvsec

GT_DT = 50_000  # 20 Hz ground truth
IMAGE_DT = 31_000  # a faster image grid (about 32 Hz), not aligned with the ground truth


class FixedFlow:
    """A policy that answers every window with ``flow_fn(window)``."""

    def __init__(self, flow_fn):
        self.flow_fn = flow_fn

    def reset(self):
        pass

    def act(self, obs, window=None):
        return self.flow_fn(window).astype(np.float32)


def _events(rng, n, size, span_us):
    h, w = size
    t = np.sort(rng.integers(0, span_us, n)).astype(np.int64)
    t[0] = 0
    return rng.integers(0, w, n), rng.integers(0, h, n), t, rng.integers(0, 2, n)


@pytest.fixture
def small_indoor(tmp_path, rng):
    """indoor_flying1 in the MVSEC layout on an 8 x 10 sensor: 1800 ground-truth maps at 20 Hz
    (90 s, so the real valid range 60-1340 applies) and images every 31 ms."""
    size, k = (8, 10), 1800
    gt_t = np.arange(k, dtype=np.int64) * GT_DT
    fx = rng.normal(0, 2, (k,) + size).astype(np.float32)
    fy = rng.normal(0, 2, (k,) + size).astype(np.float32)
    image_t = 7_000 + np.arange(int(gt_t[-1] // IMAGE_DT), dtype=np.int64) * IMAGE_DT
    images = np.zeros((len(image_t),) + size, np.uint8)
    x, y, t, p = _events(rng, 20_000, size, int(gt_t[-1]))
    path = write_mvsec(tmp_path, "indoor_flying1", x, y, t, p, images=images, image_t_us=image_t, gt=(gt_t, fx, fy))
    return path, gt_t, image_t, fx, fy


def test_scored_span_is_the_ground_truth_grid_span_not_the_image_one(small_indoor):
    path, gt_t, image_t, _, _ = small_indoor
    with MVSECReader(path) as r:
        assert mvsec_scored_span(r) == (gt_t[60], gt_t[1340])  # 3.0 s to 67.0 s
        windows = mvsec_eval_windows(r, 1, grid="images")
        inside = image_t[(image_t >= gt_t[60]) & (image_t <= gt_t[1340])]
        np.testing.assert_array_equal(windows, np.stack([inside[:-1], inside[1:]], axis=1))
        # indexing the image timestamps instead would span images 60-1340 (1.867 s to 41.5 s)
        assert windows[0, 0] > image_t[60] and windows[-1, 1] > image_t[1340]
        gt_windows = mvsec_eval_windows(r, 1, grid="gt")  # the 20 Hz mode
        np.testing.assert_array_equal(gt_windows, np.stack([gt_t[60:1340], gt_t[61:1341]], axis=1))
        flow, valid = r.flow_between(*gt_windows[5])
        np.testing.assert_allclose(flow[:, valid], np.stack([r._gt_x[65], r._gt_y[65]])[:, valid], rtol=1e-6)


def test_dt4_stride1_overlapping_and_stride4_contiguous_window_counts(small_indoor):
    path, gt_t, image_t, _, _ = small_indoor
    m = int(((image_t >= gt_t[60]) & (image_t <= gt_t[1340])).sum())  # image times in the span
    with MVSECReader(path) as r:
        overlapping = mvsec_eval_windows(r, 4, grid="images", stride=1)
        contiguous = mvsec_eval_windows(r, 4, grid="images")
    assert len(overlapping) == m - 4 and len(contiguous) == (m - 1) // 4
    np.testing.assert_array_equal(overlapping[1:, 0], overlapping[:-1, 0] + IMAGE_DT)
    np.testing.assert_array_equal(contiguous[1:, 0], contiguous[:-1, 1])
    assert (overlapping[:, 1] - overlapping[:, 0] == 4 * IMAGE_DT).all()


def test_zhu_dt1_ground_truth_is_the_containing_map_scaled(small_indoor):
    path, gt_t, image_t, fx, fy = small_indoor
    with MVSECReader(path, gt_mode="zhu") as zhu, MVSECReader(path) as chain:
        # image windows that cross a 20 Hz boundary: Zhu scales the map holding the start
        crossing = [(a, b) for a, b in zip(image_t[100:140], image_t[101:141]) if a // GT_DT != (b - 1) // GT_DT]
        assert len(crossing) > 5
        for a, b in crossing:
            i = int(a // GT_DT)
            d = np.stack([fx[i], fy[i]]).astype(np.float64)
            flow, valid = zhu.flow_between(int(a), int(b))
            assert valid.all()
            np.testing.assert_allclose(flow, d * (b - a) / GT_DT, rtol=1e-5, atol=1e-6)
            assert not np.allclose(flow, chain.flow_between(int(a), int(b))[0])
        # dt = 4 windows (124 ms) are longer than the 50 ms interval: chained in both modes
        a, b = int(image_t[200]), int(image_t[204])
        np.testing.assert_array_equal(zhu.flow_between(a, b)[0], chain.flow_between(a, b)[0])
    with pytest.raises(ValueError, match="gt_mode"):
        MVSECReader(path, gt_mode="linear")


def test_hood_rows_are_left_out_of_outdoor_scores(tmp_path, rng):
    """An outdoor recording, full 260 x 346 sensor, scored on the central 256 crop: a prediction
    right everywhere but 10 px wrong on the hood rows (>= 190 of the crop) scores AEE 0 with the
    hood left out, and the hood's share of 10 px without."""
    size = (260, 346)
    gt_t = np.arange(4, dtype=np.int64) * GT_DT
    fx = np.full((4,) + size, 1.5, np.float32)
    fy = np.full((4,) + size, -0.5, np.float32)
    image_t = np.array([0, 40_000, 80_000, 120_000], np.int64)
    x, y, t, p = _events(rng, 60_000, size, 150_000)
    path = write_mvsec(tmp_path, "outdoor_day2", x, y, t, p, images=np.zeros((4,) + size, np.uint8),
                       image_t_us=image_t, gt=(gt_t, fx, fy))
    assert mvsec_hood_row("outdoor_day2", (2, 45, 256, 256)) == 190 and mvsec_hood_row("indoor_flying1", None) is None

    def flow_fn(window):  # Zhu ground truth over the window, plus 10 px on the hood rows
        flow = np.zeros((2, 256, 256))
        share = window.duration_us / GT_DT
        flow[0], flow[1] = 1.5 * share, -0.5 * share
        flow[0, 190:] += 10.0
        return flow

    results = {}
    for hood in (True, False):
        protocol = MVSECProtocol(dt=1, hood=hood)
        (results[hood],) = evaluate(FixedFlow(flow_fn), str(path), data_format="mvsec",
                                    data_options=protocol.data_options, windows_fn=protocol.windows,
                                    scorer_fn=protocol.scorer, progress=False)
    assert results[True].windows == 3 and results[True].counts["aee"] == 3
    assert results[True].mean("aee") < 1e-5
    # without the hood rule: 10 px on the event pixels of rows >= 190, averaged with the rest
    with MVSECReader(path, crop="center256") as r:
        expected = []
        for a, b in zip(image_t[:-1], image_t[1:]):
            ev = r.events_range(r.index_at(int(a)), r.index_at(int(b)))
            mask = np.zeros((256, 256), bool)
            mask[ev.y, ev.x] = True
            expected.append(10.0 * mask[190:].sum() / mask.sum())
    assert results[False].mean("aee") == pytest.approx(np.mean(expected), rel=1e-6)
    table = results_table({"fixed": [results[True]]})
    assert "(3)" in table  # the window count beside the AEE


def test_hot_pixel_filter_drops_a_stuck_pixel_from_the_event_mask(rng):
    size = (20, 30)
    hot = HotPixelFilter(size, sigma=5.0)
    for _ in range(5):
        x, y = rng.integers(0, 30, 300), rng.integers(0, 20, 300)
        x, y = np.concatenate([x, np.full(200, 7)]), np.concatenate([y, np.full(200, 3)])  # pixel (3, 7) stuck
        mask = hot(_xy_window(x, y, size))
    assert mask[3, 7] and mask.sum() == 1
    with pytest.raises(ValueError, match="sigma"):
        HotPixelFilter(size, sigma=0)


def _xy_window(x, y, size):
    """A window of events at pixels (x, y), all at t = 0."""
    return Window.of(Events.create(x, y, np.zeros(len(x), np.int64), np.ones(len(x)), size), 0, 1)


def test_mvsec_scorer_leaves_hot_pixels_out_of_the_event_mask(rng):
    """A stuck pixel with a wrong prediction: counted without the filter, gone with it."""
    size = (20, 30)
    reader = types.SimpleNamespace(name="indoor_flying1", sequence="indoor_flying1", crop=None)
    gt = np.ones((2,) + size)
    flow = gt.copy()
    flow[:, 3, 7] += 30.0  # wrong only at the stuck pixel
    info = {"flow_gt": gt, "flow_gt_valid": np.ones(size, bool)}
    aee = {}
    for sigma in (None, 5.0):
        score = MVSECProtocol(hot_pixel_sigma=sigma).scorer(reader)
        for _ in range(4):
            x, y = rng.integers(0, 30, 300), rng.integers(0, 20, 300)
            window = _xy_window(np.concatenate([x, np.full(200, 7)]), np.concatenate([y, np.full(200, 3)]), size)
            err, mask = score(flow, info, window, size, 1.0)
        aee[sigma] = err["aee"]
        assert mask[3, 7] == (sigma is None)
    assert aee[5.0] == 0.0 and aee[None] > 0.0


def test_mvsec_protocol_refuses_bad_choices():
    with pytest.raises(ValueError, match="grid"):
        MVSECProtocol(grid="frames")
    with pytest.raises(ValueError, match="ground_truth"):
        MVSECProtocol(ground_truth="linear")
    with pytest.raises(ValueError, match="dt"):
        MVSECProtocol(dt=2)


# ----------------------------------------------------------------------------------------- DSEC
def _brute_force_dsec(flow, gt, valid):
    epe, ae = [], []
    for yy in range(gt.shape[1]):
        for xx in range(gt.shape[2]):
            if not valid[yy, xx]:
                continue
            u, v, ug, vg = flow[0, yy, xx], flow[1, yy, xx], gt[0, yy, xx], gt[1, yy, xx]
            epe.append(math.hypot(u - ug, v - vg))
            cos = (u * ug + v * vg + 1) / math.sqrt((u * u + v * v + 1) * (ug * ug + vg * vg + 1))
            ae.append(math.degrees(math.acos(max(-1.0, min(1.0, cos)))))
    epe = np.array(epe)
    return {"epe": epe.mean(), "1pe": 100 * (epe > 1).mean(), "2pe": 100 * (epe > 2).mean(),
            "3pe": 100 * (epe > 3).mean(), "ae": np.mean(ae), "n_pixels": len(epe)}


def test_dense_dsec_scores_match_a_brute_force_reference(rng):
    gt = rng.normal(0, 4, (2, 17, 23))
    flow = gt + rng.normal(0, 2, gt.shape)
    valid = rng.random((17, 23)) > 0.3
    got, want = dense_flow_error(flow, gt, valid), _brute_force_dsec(flow, gt, valid)
    assert got["n_pixels"] == want["n_pixels"] == valid.sum()
    for key in ("epe", "1pe", "2pe", "3pe", "ae"):
        assert got[key] == pytest.approx(want[key], rel=1e-9), key
    assert 0 < got["1pe"] < 100  # the synthetic errors straddle the thresholds
    assert math.isnan(dense_flow_error(flow, gt, np.zeros_like(valid))["epe"])


def _dsec_recording(tmp_path, rng, size=(24, 32)):
    """A DSEC-layout sequence with two 100 ms ground-truth maps on a small sensor."""
    x, y, t, p = _events(rng, 4_000, size, 300_000)
    path = write_dsec(tmp_path / "zurich_city_09_a" / "events" / "left", x, y, t, p)
    flow_dir = tmp_path / "zurich_city_09_a" / "flow" / "forward"
    flow_dir.mkdir(parents=True)
    maps = []
    for k in range(2):
        flow = np.round(rng.normal(0, 3, (2,) + size) * 128) / 128
        valid = rng.random(size) > 0.25
        encode_flow_png(flow_dir / f"{2 * k + 2:06d}.png", flow, valid)
        maps.append((np.where(valid, flow, 0), valid))
    (flow_dir.parent / "forward_timestamps.txt").write_text(
        "# from_timestamp_us, to_timestamp_us\n"
        f"{T_OFFSET + 50_000}, {T_OFFSET + 150_000}\n{T_OFFSET + 150_000}, {T_OFFSET + 250_000}\n")
    return path, flow_dir, maps


def test_dsec_protocol_scores_every_valid_pixel_without_an_event_mask(tmp_path, rng):
    path, flow_dir, maps = _dsec_recording(tmp_path, rng)
    prediction = rng.normal(0, 3, (2, 24, 32))
    protocol = DSECProtocol()
    (result,) = evaluate(FixedFlow(lambda w: prediction), str(path), data_format="dsec",
                         data_options={"flow_dir": str(flow_dir), "rectify": False},
                         windows_fn=protocol.windows, scorer_fn=protocol.scorer, progress=False)
    assert result.windows == 2 and result.counts["aee"] == 2
    want = [_brute_force_dsec(prediction.astype(np.float32).astype(np.float64), gt, valid) for gt, valid in maps]
    for key, col in (("aee", "epe"), ("1pe", "1pe"), ("2pe", "2pe"), ("3pe", "3pe"), ("ae", "ae")):
        assert result.mean(key) == pytest.approx(np.mean([w[col] for w in want]), rel=1e-6), key
    table = dsec_table({"fixed": [result]})
    assert "| EPE | 1PE % | 2PE % | 3PE % | AE deg | windows |" in table and "| 2 |" in table


def test_test_timestamps_csv_reads_the_file_index_column(tmp_path):
    csv = tmp_path / "thun_01_a.csv"
    csv.write_text("# from_timestamp_us, to_timestamp_us, file_index\n"
                   "49599300523, 49599400524, 820\n49599800527, 49599900528, 830\n")
    rows = read_test_timestamps(csv)
    assert rows.dtype == np.int64
    np.testing.assert_array_equal(rows, [[49599300523, 49599400524, 820], [49599800527, 49599900528, 830]])
    csv.write_text("# from, to\n1, 2\n")
    with pytest.raises(FormatError, match="file_index"):
        read_test_timestamps(csv)
    csv.write_text("1, 2, 5\n3, 4, 5\n")
    with pytest.raises(FormatError, match="repeat"):
        read_test_timestamps(csv)


def test_submission_pngs_in_the_benchmark_layout_decode_back_to_the_flows(tmp_path, rng):
    """The test windows come from the CSV; each window's flow lands in
    <sequence>/<file_index:06d>.png and decodes through our reader to within 1/128 px."""
    size = (24, 32)
    x, y, t, p = _events(rng, 3_000, size, 400_000)
    path = write_dsec(tmp_path / "test" / "interlaken_00_b" / "events" / "left", x, y, t, p)
    stamps = tmp_path / "test_forward_optical_flow_timestamps"
    stamps.mkdir()
    rows = [(T_OFFSET + 20_000, T_OFFSET + 120_000, 820), (T_OFFSET + 220_000, T_OFFSET + 320_000, 830)]
    (stamps / "interlaken_00_b.csv").write_text("# from_timestamp_us, to_timestamp_us, file_index\n"
                                                + "".join(f"{a}, {b}, {k}\n" for a, b, k in rows))
    flows = {row[0]: rng.uniform(-60, 60, (2,) + size) for row in rows}
    protocol = DSECProtocol(test_timestamps=stamps)
    writer = DSECSubmissionWriter(tmp_path / "submission", protocol)
    (result,) = evaluate(FixedFlow(lambda w: flows[w.t_start]), str(path), data_format="dsec",
                         data_options={"sensor_size": size, "rectify": False}, windows_fn=protocol.windows,
                         scorer_fn=protocol.scorer, flow_sink=writer, progress=False)
    assert result.windows == 2 and writer.clipped == 0
    names = sorted(p.relative_to(tmp_path / "submission").as_posix() for p in (tmp_path / "submission").rglob("*.png"))
    assert names == ["interlaken_00_b/000820.png", "interlaken_00_b/000830.png"]
    for a, _, k in rows:
        decoded, valid = decode_flow_png(tmp_path / "submission" / "interlaken_00_b" / f"{k:06d}.png")
        assert valid.all() and decoded.shape == (2,) + size
        assert np.abs(decoded - flows[a].astype(np.float32)).max() <= 1 / 256 + 1e-6  # nearest 1/128 px
    with pytest.raises(ValueError, match="not one of the test timestamps"):
        writer(types.SimpleNamespace(name="interlaken_00_b"), _xy_window([0], [0], size), np.zeros((2,) + size))
    with pytest.raises(ValueError, match="test timestamps"):
        DSECSubmissionWriter(tmp_path / "x", DSECProtocol())


# --------------------------------------------------------------------------- scripts/evaluate.py
def _evaluate_script():
    from evflow_cli.commands import evaluate as evaluate_script

    return evaluate_script


def test_evaluate_script_mvsec_tables_dt1_dt4_both_strides_with_window_counts(tmp_path, rng, monkeypatch):
    import json

    from envs.readers import mvsec as mvsec_module

    size = (260, 346)
    gt_t = np.arange(12, dtype=np.int64) * GT_DT
    fx = rng.normal(0, 1, (12,) + size).astype(np.float32)
    fy = rng.normal(0, 1, (12,) + size).astype(np.float32)
    image_t = 5_000 + np.arange(17, dtype=np.int64) * IMAGE_DT
    x, y, t, p = _events(rng, 40_000, size, int(gt_t[-1]))
    write_mvsec(tmp_path, "indoor_flying2", x, y, t, p, images=np.zeros((17,) + size, np.uint8), image_t_us=image_t,
                gt=(gt_t, fx, fy))
    monkeypatch.setitem(mvsec_module.MVSEC_VALID_FRAMES, "indoor_flying2", (2, 10))  # a valid range this file holds
    out = tmp_path / "eval"
    _evaluate_script().main(["--zero", "--mvsec", str(tmp_path), "--out", str(out), "--no-progress", "--pictures", "0"])
    results = json.loads((out / "results.json").read_text())
    with MVSECReader(tmp_path / "indoor_flying2_data.hdf5") as r:
        expected = {"dt1": len(mvsec_eval_windows(r, 1, grid="images")),
                    "dt4": len(mvsec_eval_windows(r, 4, grid="images")),
                    "dt4_stride1": len(mvsec_eval_windows(r, 4, grid="images", stride=1))}
    assert expected["dt4_stride1"] > expected["dt4"] > 0
    for key, n in expected.items():
        assert results["overall"][key]["windows"] == n, key
    table = (out / "table.md").read_text()
    assert "MVSEC dt = 4 image frames, stride 1, zhu ground truth" in table
    assert f"({expected['dt4_stride1']})" in table and f"({expected['dt1']})" in table


def test_evaluate_script_writes_a_dsec_submission(tmp_path, rng):
    size = (480, 640)
    x, y, t, p = _events(rng, 2_000, size, 300_000)
    path = write_dsec(tmp_path / "test" / "thun_01_a" / "events" / "left", x, y, t, p)
    stamps = tmp_path / "stamps"
    stamps.mkdir()
    (stamps / "thun_01_a.csv").write_text("# from_timestamp_us, to_timestamp_us, file_index\n"
                                          f"{T_OFFSET + 10_000}, {T_OFFSET + 110_000}, 4\n"
                                          f"{T_OFFSET + 150_000}, {T_OFFSET + 250_000}, 14\n")
    _evaluate_script().main(["--zero", "--protocol", "dsec", "--format", "dsec", "--data", str(path),
                             "--dsec-test-timestamps", str(stamps), "--dsec-submission", str(tmp_path / "sub"),
                             "--out", str(tmp_path / "eval"), "--no-progress", "--pictures", "0"])
    for k in (4, 14):
        flow, valid = decode_flow_png(tmp_path / "sub" / "thun_01_a" / f"{k:06d}.png")
        assert flow.shape == (2,) + size and valid.all() and not flow.any()  # zero flow, every pixel predicted
    with pytest.raises(SystemExit, match="--dsec-test-timestamps"):
        _evaluate_script().main(["--zero", "--protocol", "dsec", "--data", str(path),
                                 "--dsec-submission", str(tmp_path)])
