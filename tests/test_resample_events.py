"""tools/resample_events.py: a Hagenaars recording with its events thinned or repeated, read back
through the project's reader; the ground truth is untouched and a bad file is refused whole."""

import h5py
import numpy as np
import pytest

from envs.readers import open_recording
from tests.conftest import load_script
from tests.test_readers import _stream, write_hagenaars


@pytest.fixture(scope="module")
def resample_events():
    return load_script("tools/resample_events.py")


def _read(path):
    with open_recording(path) as reader:
        return reader.events_range(0, reader.num_events), reader.flow_between(0, 100_000)


def test_thinning_keeps_a_seeded_subset_and_repeating_stacks_each_event(resample_events, tmp_path):
    x, y, t, p = _stream(np.random.default_rng(1), 4_000, (20, 30), 300_000)
    flow = np.random.default_rng(2).normal(size=(2, 20, 30))
    source = write_hagenaars(tmp_path / "rec.h5", x, y, t, p, flows=[("flow_dt1", 100_000, flow, 0)])
    events, gt = _read(source)

    thinned = tmp_path / "out" / "keep.h5"
    n = resample_events.resample(source, thinned, keep=0.3, seed=7)
    kept, gt_kept = _read(thinned)
    chosen = np.random.default_rng(7).random(len(events.t)) < 0.3  # the documented draw
    assert n == chosen.sum() == len(kept.t) and abs(n - 1200) < 150
    for field in ("x", "y", "t", "p"):
        np.testing.assert_array_equal(getattr(kept, field), getattr(events, field)[chosen])
    np.testing.assert_array_equal(gt_kept[0], gt[0])
    with h5py.File(thinned) as f:
        assert f.attrs["num_events"] == n

    repeated = tmp_path / "x3.h5"
    assert resample_events.resample(source, repeated, repeat=3) == 3 * len(events.t)
    stacked, _ = _read(repeated)
    for field in ("x", "y", "t", "p"):
        np.testing.assert_array_equal(getattr(stacked, field), np.repeat(getattr(events, field), 3))


def test_refusals_leave_nothing_behind(resample_events, tmp_path):
    other = tmp_path / "other.h5"
    with h5py.File(other, "w") as f:
        f["events/x"] = np.zeros(3)
    with pytest.raises(ValueError, match="not a Hagenaars"):
        resample_events.resample(other, tmp_path / "out.h5", keep=0.5)
    with pytest.raises(ValueError, match="keep must be"):
        resample_events.resample(other, tmp_path / "out.h5", keep=0.0)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["other.h5"]
