"""Tests for losses/metrics.py: AEE / outlier %, FWL, RSAT (docs/method.md, "Metrics")."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from envs.events import Events
from envs.windows import Window
from losses import EventBatch, flow_error, flow_error_torch, fwl, fwl_torch, rsat, rsat_torch


def test_flow_error_by_hand():
    H, W = 4, 5
    gt = np.zeros((2, H, W))
    gt[0] = 10.0  # every pixel valid (not both components 0)
    gt[:, 3, 4] = 0.0  # invalid pixel
    flow = gt.copy()
    flow[0, 0, 0] += 4.0  # error 4 > 3 and > 0.5: outlier
    flow[1, 0, 1] += 3.0  # error 3: not > 3
    flow[0, 1, 1] -= 0.4  # small error
    flow[0, 3, 4] = 100.0  # invalid gt: ignored
    ev = np.ones((H, W), bool)
    ev[2, 2] = False  # no event there: ignored
    flow[0, 2, 2] += 50.0
    out = flow_error(flow, gt, None, ev)
    n = H * W - 2
    assert out["n_pixels"] == n
    assert out["aee"] == pytest.approx((4 + 3 + 0.4) / n)
    assert out["outlier_pct"] == pytest.approx(100.0 / n)
    # explicit valid mask agrees with the derived one
    assert flow_error(flow, gt, np.any(gt != 0, axis=0), ev) == out


def test_outlier_needs_both_absolute_and_relative_error():
    gt = np.zeros((2, 1, 2))
    gt[0] = [100.0, 20.0]
    flow = gt.copy()
    flow[0] += 4.0  # 4 px: > 3 px, but 4 % of 100 (not outlier) and 20 % of 20 (outlier)
    out = flow_error(flow, gt, None, None)
    assert out["outlier_pct"] == pytest.approx(50.0)


def test_dt_ratio_and_crop():
    rng = np.random.default_rng(0)
    H, W = 10, 12
    gt = rng.normal(0, 2, (2, H, W))
    flow = gt / 4.0  # predicted over a window 4x shorter than the gt interval
    assert flow_error(flow, gt, None, None, dt_ratio=4.0)["aee"] == pytest.approx(0, abs=1e-12)
    flow2 = gt.copy()
    flow2[:, :2] += 10  # error only outside the central crop rows 2..7
    out = flow_error(flow2, gt, None, None, crop=(6, 8))
    assert out["n_pixels"] == 48 and out["aee"] == pytest.approx(0, abs=1e-12)
    with pytest.raises(ValueError, match="crop"):
        flow_error(flow2, gt, None, None, crop=(20, 8))


def test_flow_error_no_pixels_and_bad_input():
    gt = np.zeros((2, 3, 3))
    out = flow_error(gt, gt, None, None)
    assert out["n_pixels"] == 0 and math.isnan(out["aee"]) and math.isnan(out["outlier_pct"])
    with pytest.raises(ValueError, match="must both be"):
        flow_error(np.zeros((2, 3, 4)), gt, None, None)
    with pytest.raises(ValueError, match="event_mask"):
        flow_error(gt, gt, None, np.ones((3, 4), bool))
    bad = gt.copy()
    bad[0, 0, 0] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        flow_error(bad, gt + 1, None, None)


def test_flow_error_torch_batched_matches_numpy():
    rng = np.random.default_rng(1)
    f, g = rng.normal(0, 3, (3, 2, 8, 9)), rng.normal(0, 3, (3, 2, 8, 9))
    ev = rng.random((3, 8, 9)) > 0.3
    out = flow_error_torch(torch.from_numpy(f), torch.from_numpy(g), None, torch.from_numpy(ev),
                           dt_ratio=2.0, crop=(6, 6))
    for b in range(3):
        one = flow_error(f[b], g[b], None, ev[b], dt_ratio=2.0, crop=(6, 6))
        assert out["aee"][b].item() == pytest.approx(one["aee"])
        assert out["outlier_pct"][b].item() == pytest.approx(one["outlier_pct"])
        assert out["n_pixels"][b].item() == one["n_pixels"]


def dots(v=(10.0, 5.0), H=48, W=48, seed=0, dur=10_000):
    rng = np.random.default_rng(seed)
    xs, ys, ts, ps = [], [], [], []
    for d in range(10):
        x0, y0 = rng.uniform(5, 30), rng.uniform(5, 35)
        t = np.sort(rng.integers(0, dur, 50))
        xs.append(np.round(x0 + t / dur * v[0]))
        ys.append(np.round(y0 + t / dur * v[1]))
        ts.append(t)
        ps.append(np.full(50, 1 if d % 2 else -1))
    o = np.argsort(np.concatenate(ts), kind="stable")
    c = lambda a: np.concatenate(a)[o]  # noqa: E731
    return Window.of(Events.create(c(xs), c(ys), c(ts), c(ps), (H, W)), 0, dur), (H, W)


def test_fwl_and_rsat_zero_flow_is_one_and_true_flow_improves():
    v = (10.0, 5.0)
    ev, (H, W) = dots(v)
    zero = np.zeros((2, H, W))
    assert fwl(zero, ev, (H, W)) == pytest.approx(1.0, abs=1e-12)
    assert rsat(zero, ev, (H, W)) == pytest.approx(1.0, abs=1e-12)
    true = np.zeros((2, H, W))
    true[0], true[1] = v
    assert fwl(true, ev, (H, W)) > 1.5  # sharper
    assert rsat(true, ev, (H, W)) < 1.0
    # the sensor size defaults to the window's own
    assert fwl(true, ev) == fwl(true, ev, (H, W)) and rsat(true, ev) == rsat(true, ev, (H, W))


def test_fwl_rsat_by_hand_and_empty_window():
    H, W = 4, 6
    # two ON events at pixel (row 1, col 1) at tau 0 and 0.5: flow (2, 0) warps to s = 1
    ev = Window.of(Events.create([1, 1], [1, 1], [0, 50], [1, 1], (H, W)), 0, 100)
    flow = np.zeros((2, H, W))
    flow[0] = 2.0  # event 0 -> col 3, event 1 -> col 2
    zero_img = np.zeros(H * W); zero_img[W + 1] = 2  # noqa: E702
    flow_img = np.zeros(H * W); flow_img[W + 3] = 1; flow_img[W + 2] = 1  # noqa: E702
    assert fwl(flow, ev, (H, W)) == pytest.approx(flow_img.var() / zero_img.var())
    sat_zero = (0.5 / (2 + 1e-9)) ** 2 / (1 + 1e-9)  # A = 0 + 0.5, C = 2
    sat_flow = ((0.0 / (1 + 1e-9)) ** 2 + (0.5 / (1 + 1e-9)) ** 2) / (2 + 1e-9)
    assert rsat(flow, ev, (H, W)) == pytest.approx(sat_flow / sat_zero)
    empty = Window.of(Events.create([], [], [], [], (H, W)), 0, 100)
    assert math.isnan(fwl(flow, empty, (H, W))) and math.isnan(rsat(flow, empty, (H, W)))
    with pytest.raises(ValueError, match="expected"):
        fwl(np.zeros((2, 3, 3)), ev, (H, W))
    with pytest.raises(TypeError, match="Window.of"):  # a window dict is no longer taken
        fwl(flow, {"x": [1], "y": [1], "t": [0], "p": [1], "t_start": 0, "t_end": 100}, (H, W))


def test_fwl_rsat_torch_batched():
    ev1, (H, W) = dots(seed=1)
    ev2, _ = dots(seed=2)
    batch = EventBatch.from_windows([ev1, ev2], dtype=torch.float64)
    flow = torch.zeros(2, 2, H, W, dtype=torch.float64)
    flow[:, 0], flow[:, 1] = 10.0, 5.0
    got_fwl, got_rsat = fwl_torch(flow, batch), rsat_torch(flow, batch)
    for b, ev in enumerate((ev1, ev2)):
        assert got_fwl[b].item() == pytest.approx(fwl(flow[b].numpy(), ev, (H, W)))
        assert got_rsat[b].item() == pytest.approx(rsat(flow[b].numpy(), ev, (H, W)))
