"""A policy's flow times a constant: a calibration of its magnitude (``tools/cheap_modes.py``,
``gain:G``)."""

from __future__ import annotations

import numpy as np

from envs.windows import Window

from ..policy import as_flow_policy

__all__ = ["GainPolicy"]


class GainPolicy:
    """The wrapped policy's flow multiplied by ``gain``."""

    def __init__(self, policy, gain: float) -> None:
        self.policy, self.gain = as_flow_policy(policy), float(gain)
        self.input_key = getattr(policy, "input_key", "count_image")
        self.voxel_bins = getattr(policy, "voxel_bins", 5)
        self.device = getattr(policy, "device", "cpu")

    def reset(self, mask=None) -> None:
        self.policy.reset(mask)

    def act(self, obs, window: Window | None = None) -> np.ndarray:
        """``gain`` times the wrapped policy's flow (``agents.policy.FlowPolicy``)."""
        return self.policy.act(obs, window) * self.gain
