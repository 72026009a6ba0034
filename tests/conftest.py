"""Shared fixtures: small random recordings built in memory."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from envs.events import Events

torch.set_num_threads(1)


def random_events(rng: np.random.Generator, n: int, sensor_size=(20, 30), t_span=(0, 100_000)) -> Events:
    """n events, uniform in space and time, sorted in time, with repeated timestamps."""
    h, w = sensor_size
    t = np.sort(rng.integers(t_span[0], t_span[1], n))
    return Events.create(rng.integers(0, w, n), rng.integers(0, h, n), t, rng.integers(0, 2, n), sensor_size)


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(1234)


@pytest.fixture(autouse=True, scope="session")
def _synthetic_cache(tmp_path_factory):
    """Keep the tests' simulated sequences out of the user's cache (one cache per session)."""
    import os

    old = os.environ.get("EVFLOW_CACHE")
    os.environ["EVFLOW_CACHE"] = str(tmp_path_factory.mktemp("evflow-cache"))
    yield
    if old is None:
        os.environ.pop("EVFLOW_CACHE", None)
    else:
        os.environ["EVFLOW_CACHE"] = old
