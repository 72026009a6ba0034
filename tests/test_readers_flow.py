"""Ground truth for arbitrary windows from per-interval displacement maps (envs.readers.flowgt):
linear scaling inside one interval, nearest-neighbour chaining across intervals."""

from __future__ import annotations

import math

import numpy as np
import pytest

from envs.readers.flowgt import flow_from_displacements, valid_of

TIMES = np.array([0, 50_000, 100_000, 150_000, 200_000])


def slow_reference(maps, times, t0, t1):
    """Pixel by pixel, interval by interval, in plain Python: the oracle."""
    _, h, w = maps[0].shape
    flow = np.zeros((2, h, w))
    valid = np.zeros((h, w), bool)
    for r in range(h):
        for c in range(w):
            x, y, ok, tc = float(c), float(r), True, t0
            while tc < t1:
                i = max(k for k in range(len(times) - 1) if times[k] <= tc)
                end = min(times[i + 1], t1)
                xi, yi = math.floor(x + 0.5), math.floor(y + 0.5)
                if not (0 <= xi < w and 0 <= yi < h):
                    ok = False
                    break
                dx, dy = maps[i][0, yi, xi], maps[i][1, yi, xi]
                if dx == 0 and dy == 0:
                    ok = False
                frac = (end - tc) / (times[i + 1] - times[i])
                x, y, tc = x + frac * dx, y + frac * dy, end
            if ok:
                valid[r, c] = True
                flow[:, r, c] = (x - c, y - r)
    return flow, valid


def run(maps, t0, t1, times=TIMES):
    return flow_from_displacements(lambda i: maps[i], times, t0, t1)


def test_constant_translation_dt1_dt4_and_borders():
    maps = [np.stack([np.full((6, 9), 1.5), np.full((6, 9), -0.5)])] * 4
    flow, valid = run(maps, 0, 50_000)
    assert valid.all() and np.allclose(flow[0], 1.5) and np.allclose(flow[1], -0.5)
    flow, valid = run(maps, 0, 200_000)  # dt = 4
    assert np.allclose(flow[0][valid], 6.0) and np.allclose(flow[1][valid], -2.0)
    # lookups at x + 1.5k, y - 0.5k (k = 0..3) must stay on the 6 x 9 sensor
    ys, xs = np.mgrid[0:6, 0:9]
    inside = np.ones((6, 9), bool)
    for k in range(4):
        inside &= (np.floor(xs + 1.5 * k + 0.5) <= 8) & (np.floor(ys - 0.5 * k + 0.5) >= 0)
    np.testing.assert_array_equal(valid, inside)
    assert (flow[:, ~valid] == 0).all()


def test_scaling_inside_one_interval():
    d = np.random.default_rng(0).normal(size=(2, 5, 7))
    flow, valid = run([d] * 4, 60_000, 70_000)
    np.testing.assert_allclose(flow, (d * 0.2).astype(np.float32), rtol=1e-6)
    assert valid.all()


def test_motion_changing_between_intervals_is_looked_up_where_the_pixel_moved():
    h, w = 4, 12
    ys, xs = np.mgrid[0:h, 0:w].astype(float)
    first = np.stack([np.ones((h, w)), np.zeros((h, w))])  # 1 px right
    second = np.stack([np.zeros((h, w)), xs / 8.0])  # down by x / 8, x read AFTER the first move
    maps = [first, second, first, second]
    flow, valid = run(maps, 0, 100_000)
    np.testing.assert_array_equal(valid, xs <= w - 2)  # x + 1 must stay on the sensor
    np.testing.assert_allclose(flow[0][valid], 1.0)
    np.testing.assert_allclose(flow[1][valid], ((xs + 1) / 8.0)[valid])  # not x / 8
    # start half-way through the first interval: moved 0.5 px, nearest pixel is still x + 1
    flow, valid = run(maps, 25_000, 100_000)
    np.testing.assert_allclose(flow[0][valid], 0.5)
    np.testing.assert_allclose(flow[1][valid], ((xs + 1) / 8.0)[valid])
    # end a quarter into the second interval
    flow, _ = run(maps, 0, 62_500)
    np.testing.assert_allclose(flow[1][valid], ((xs + 1) / 32.0)[valid])


def test_random_fields_match_the_slow_reference():
    rng = np.random.default_rng(5)
    maps = [rng.normal(0, 1.2, (2, 7, 8)) for _ in range(4)]
    maps[2][:, 3, 4] = 0.0  # an invalid pixel in the middle
    for t0, t1 in [(0, 200_000), (10_000, 190_000), (50_000, 150_000), (75_000, 80_000), (120_000, 200_000)]:
        flow, valid = run(maps, t0, t1)
        ref_flow, ref_valid = slow_reference(maps, TIMES, t0, t1)
        np.testing.assert_array_equal(valid, ref_valid)
        np.testing.assert_allclose(flow, ref_flow, atol=1e-5)


def test_windows_outside_the_ground_truth_have_none():
    maps = [np.ones((2, 2, 2))] * 4
    assert run(maps, -1, 50_000) is None
    assert run(maps, 150_000, 200_001) is None
    assert run(maps, 10, 10) is None
    nan = np.ones((2, 2, 2))
    nan[0, 0, 0] = np.nan
    assert not valid_of(nan)[0, 0] and valid_of(nan).sum() == 3


@pytest.mark.parametrize("dt", [1, 4])
def test_dt_windows_over_many_intervals_compose(dt):
    """A dt-window equals the composition of its dt one-interval windows for constant fields."""
    times = np.arange(9) * 10
    maps = [np.stack([np.full((3, 40), 0.75 * (k + 1)), np.zeros((3, 40))]) for k in range(8)]
    flow, valid = flow_from_displacements(lambda i: maps[i], times, 0, 10 * dt)
    assert np.allclose(flow[0][valid], sum(0.75 * (k + 1) for k in range(dt)))
