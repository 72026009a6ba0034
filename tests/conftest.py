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


def pytest_collection_modifyitems(config, items):
    """With the compiled CPU kernels switched off (EVFLOW_CPU_KERNELS=0: the suite on the path CUDA
    takes), the tests of the kernels themselves are skipped, saying why."""
    from losses import cpu_kernels_enabled

    if cpu_kernels_enabled():
        return
    skip = pytest.mark.skip(reason="tests the compiled CPU kernels, switched off here (EVFLOW_CPU_KERNELS=0)")
    for item in items:
        if "cpu_kernels" in item.keywords:
            item.add_marker(skip)


def load_script(relative_path: str):
    """A script of the checkout (``tools/x.py``, ``scripts/x.py``: not a package) as a module."""
    import importlib.util
    from pathlib import Path

    path = Path(__file__).resolve().parents[1] / relative_path
    spec = importlib.util.spec_from_file_location(path.stem, path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


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
