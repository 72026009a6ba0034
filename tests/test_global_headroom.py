"""tools/global_headroom.py: the oracle corrections on fields whose answers are known by construction,
and its AEE column against scripts/evaluate.py's own."""

import numpy as np
import pytest

from tests.conftest import load_script

H, W = 24, 32


@pytest.fixture(scope="module")
def gh():
    return load_script("tools/global_headroom.py")


def affine_field(a: tuple[float, ...]) -> np.ndarray:
    ys, xs = np.mgrid[0:H, 0:W].astype(np.float64)
    x, y = xs / W - 0.5, ys / H - 0.5
    return np.stack([a[0] + a[1] * x + a[2] * y, a[3] + a[4] * x + a[5] * y])


def rough_field(seed: int) -> np.ndarray:
    return np.random.default_rng(seed).normal(0, 2, (2, H, W))


def mask(seed: int = 3, share: float = 0.3) -> np.ndarray:
    return np.random.default_rng(seed).random((H, W)) < share


def test_a_constant_offset_is_removed_by_both_corrections(gh):
    gt = rough_field(0)
    pred = gt + np.array([1.5, -2.0])[:, None, None]
    out = gh.headroom(pred, gt, mask())
    assert out["aee"] == pytest.approx(2.5)
    assert out["aee_translation"] == pytest.approx(0, abs=1e-9)
    assert out["aee_affine"] == pytest.approx(0, abs=1e-9)
    assert out["aee_truth_affine"] > 1.0  # the rough truth is far from one affine motion


def test_an_affine_truth_is_its_own_fit_and_an_affine_error_is_removed(gh):
    gt = affine_field((2.0, 3.0, -1.0, -1.0, 0.5, 4.0))
    pred = gt + affine_field((0.3, -2.0, 1.0, 0.1, 0.0, -3.0))
    out = gh.headroom(pred, gt, mask())
    assert out["aee_truth_affine"] == pytest.approx(0, abs=1e-9)
    assert out["aee_affine"] == pytest.approx(0, abs=1e-9)
    assert 0 < out["aee_translation"] < out["aee"]
    assert out["aee_own_affine"] == pytest.approx(out["aee"])  # an affine prediction is its own fit


def test_the_affine_fit_matches_normal_equations_written_out(gh):
    gt, pred, m = rough_field(1), rough_field(2), mask(4)
    ys, xs = np.nonzero(m)
    basis = [np.ones(len(xs)), xs / W - 0.5, ys / H - 0.5]
    normal = np.array([[np.sum(a * b) for b in basis] for a in basis])
    expected = []
    for c in range(2):
        residual = gt[c, ys, xs] - pred[c, ys, xs]
        coef = np.linalg.solve(normal, np.array([np.sum(a * residual) for a in basis]))
        expected.append(pred[c, ys, xs] + sum(k * a for k, a in zip(coef, basis)))
    slow = np.mean(np.hypot(gt[0, ys, xs] - expected[0], gt[1, ys, xs] - expected[1]))
    assert gh.headroom(pred, gt, m)["aee_affine"] == pytest.approx(slow, rel=1e-9)


def test_too_few_pixels_are_refused(gh):
    m = np.zeros((H, W), bool)
    m[0, :2] = True
    with pytest.raises(ValueError, match="at least 3 scored pixels, got 2"):
        gh.headroom(rough_field(0), rough_field(1), m)


def test_its_aee_column_is_the_evaluation_aee(gh):
    from agents.evaluation import evaluate

    plain = evaluate(None, "synthetic-mini", window_size=1, max_windows=3, progress=False)
    ours = evaluate(None, "synthetic-mini", window_size=1, max_windows=3, progress=False, scorer_fn=gh.make_scorer())
    assert [r.name for r in ours] == [r.name for r in plain]
    for a, b in zip(plain, ours):
        assert b.mean("aee") == pytest.approx(a.mean("aee"), rel=1e-6)
        assert b.mean("aee_own_affine") == pytest.approx(b.mean("aee"), rel=1e-9)  # zero flow fits to zero
        assert b.mean("aee_affine") <= b.mean("aee") + 1e-9
