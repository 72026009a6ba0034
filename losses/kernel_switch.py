"""One switch for every compiled CPU kernel (numba) of the project, in ``losses/`` and ``agents/``.

The kernels run on CPU tensors only; on CUDA the same functions take their plain torch
expressions, and the networks keep NCHW activations. With the switch off the CPU takes that
path too, so the code a GPU runs is exercised on a machine without one:
``EVFLOW_CPU_KERNELS=0 pytest`` runs the whole suite that way, and ``tests/test_kernels_off.py``
holds the two paths to each other (networks, losses, a training step) in every run.

    with cpu_kernels(False):        # the torch path, as on CUDA
        loss = hmc_loss(flow, events)
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from contextlib import contextmanager

import torch

__all__ = ["ENV_VAR", "cpu_kernels", "cpu_kernels_enabled", "set_cpu_kernels", "use_cpu_kernels"]

#: the environment variable read at import: 1 / on (default) or 0 / off
ENV_VAR = "EVFLOW_CPU_KERNELS"
_ON, _OFF = ("1", "on", "true", "yes", ""), ("0", "off", "false", "no")


def _from_environment() -> bool:
    value = os.environ.get(ENV_VAR, "1").strip().lower()
    if value not in _ON + _OFF:
        raise ValueError(f"{ENV_VAR}={value!r}: expected 1 / on (compiled CPU kernels) or 0 / off (the torch path)")
    return value in _ON


_enabled = _from_environment()


def cpu_kernels_enabled() -> bool:
    """Whether CPU tensors go through the compiled kernels (True unless switched off)."""
    return _enabled


def use_cpu_kernels(tensor: torch.Tensor) -> bool:
    """Whether a computation on ``tensor`` takes the compiled kernels: the switch is on and the
    tensor is a float32 or float64 CPU tensor (anything else: the torch expressions)."""
    return _enabled and tensor.device.type == "cpu" and tensor.dtype in (torch.float32, torch.float64)


def set_cpu_kernels(enabled: bool) -> bool:
    """Switch the compiled CPU kernels on or off for this process; returns the previous setting."""
    global _enabled
    previous, _enabled = _enabled, bool(enabled)
    return previous


@contextmanager
def cpu_kernels(enabled: bool) -> Iterator[None]:
    """The compiled CPU kernels on or off inside the ``with`` block, restored after it."""
    previous = set_cpu_kernels(enabled)
    try:
        yield
    finally:
        set_cpu_kernels(previous)
