"""tools/occlusion_share.py: the split of the AEE into pixels that keep their scene layer and
pixels that change it, summed over windows."""

import pytest

from tests.conftest import load_script


@pytest.fixture(scope="module")
def occlusion_share():
    return load_script("tools/occlusion_share.py")


def test_the_split_is_pooled_over_windows_by_pixel(occlusion_share):
    # (sequence, kept pixels, their error sum, zero flow's error sum, changed pixels, error sum, zero's)
    rows = [("a", 10, 5.0, 20.0, 0, 0.0, 0.0), ("b", 30, 9.0, 40.0, 20, 30.0, 10.0)]
    out = occlusion_share.summarise(rows)
    assert out["pixels"] == 60
    assert out["changed_pct"] == pytest.approx(100 * 20 / 60)
    assert out["aee"] == pytest.approx((5 + 9 + 30) / 60)
    assert out["aee_kept"] == pytest.approx(14 / 40) and out["aee_changed"] == pytest.approx(30 / 20)
    assert out["zero_kept"] == pytest.approx(60 / 40) and out["zero_changed"] == pytest.approx(10 / 20)
    assert out["error_on_changed_pct"] == pytest.approx(100 * 30 / 44)


def test_no_pixels_give_no_numbers_rather_than_zero_errors(occlusion_share):
    for rows in ([], [("a", 0, 0.0, 0.0, 0, 0.0, 0.0)]):
        out = occlusion_share.summarise(rows)
        assert out["pixels"] == 0
        assert all(out[key] is None for key in out if key != "pixels")
    only_kept = occlusion_share.summarise([("a", 4, 2.0, 8.0, 0, 0.0, 0.0)])
    assert only_kept["aee_changed"] is None and only_kept["changed_pct"] == 0 and only_kept["aee"] == 0.5
