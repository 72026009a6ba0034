import numpy as np
import pytest

from envs.events import EventError, Events, normalize_polarity
from tests.conftest import random_events


def test_polarity_conventions_agree():
    expected = np.array([1, -1, 1, -1], np.int8)
    np.testing.assert_array_equal(normalize_polarity(np.array([1, 0, 1, 0])), expected)
    np.testing.assert_array_equal(normalize_polarity(np.array([1, -1, 1, -1])), expected)
    np.testing.assert_array_equal(normalize_polarity(np.array([True, False, True, False])), expected)


def test_create_converts_to_canonical_dtypes():
    ev = Events.create([1, 2], [0, 3], [5.0, 7.0], [0, 1], (4, 5))
    assert ev.x.dtype == np.int16 and ev.y.dtype == np.int16
    assert ev.t.dtype == np.int64 and ev.p.dtype == np.int8
    np.testing.assert_array_equal(ev.p, [-1, 1])


@pytest.mark.parametrize(
    "kwargs, field, index",
    [
        (dict(x=[0, 1, 2], y=[0, 0, 0], t=[0, 5, 4], p=[1, 1, 1]), "'t'", "index 2"),
        (dict(x=[0, 5, 9], y=[0, 0, 0], t=[0, 1, 2], p=[1, 1, 1]), "'x'", "index 1"),
        (dict(x=[0, 1, 2], y=[0, -1, 0], t=[0, 1, 2], p=[1, 1, 1]), "'y'", "index 1"),
        (dict(x=[0, 1, 2], y=[0, 0, 0], t=[0, 1, 2], p=[1, 2, 1]), "'p'", "index 1"),
        (dict(x=[0, 1, 2], y=[0, 0, 0], t=[0, np.nan, 2.0], p=[1, 1, 1]), "'t'", "index 1"),
    ],
)
def test_violations_name_field_and_first_bad_index(kwargs, field, index):
    with pytest.raises(EventError) as err:
        Events.create(**kwargs, sensor_size=(4, 5), source="rec.h5")
    message = str(err.value)
    assert field in message and index in message and "rec.h5" in message


def test_length_mismatch_is_named():
    with pytest.raises(EventError, match="'x' has 2 entries"):
        Events.create([0, 1], [0, 0, 0], [0, 1, 2], [1, 1, 1], (4, 5))


def test_slice_time_matches_boolean_mask(rng):
    ev = random_events(rng, 5000)
    for t0, t1 in [(0, 100), (1234, 56789), (99_990, 200_000), (-5, 3), (500, 500)]:
        part = ev.slice_time(t0, t1)
        keep = (ev.t >= t0) & (ev.t < t1)
        np.testing.assert_array_equal(part.t, ev.t[keep])
        np.testing.assert_array_equal(part.x, ev.x[keep])


def test_tau_is_normalised_time():
    ev = Events.create([0, 0], [0, 0], [100, 150], [1, 1], (2, 2))
    np.testing.assert_allclose(ev.tau(100, 200), [0.0, 0.5])
