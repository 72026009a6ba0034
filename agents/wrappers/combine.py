"""Several policies on each window, one flow out: their mean, or the one the window's events
prefer (the lowest L_HMC as the env scores it) (``tools/cheap_modes.py``, ``avg:A+B`` and
``pick:A+B``)."""

from __future__ import annotations

from typing import Literal, get_args

import numpy as np
import torch

from envs.windows import Window
from losses import window_loss

from ..policy import ZeroFlowPolicy, as_flow_policy

__all__ = ["CombinedPolicy"]

Combination = Literal["avg", "pick"]


class CombinedPolicy:
    """Every policy of ``policies`` (None: zero flow) acts on each window; ``how``: "avg", their
    mean flow; "pick", the flow with the lowest loss on the window's events
    (``losses.window_loss``: L_HMC, paper weights, border rule, flow scaling max(H, W)), the
    first policy's on a window without events. ``picked[i]``: how many windows took policy i's."""

    def __init__(self, policies: list, how: Combination) -> None:
        if how not in get_args(Combination):
            raise ValueError(f"how must be one of {get_args(Combination)}, got {how!r}")
        first = next(p for p in policies if p is not None)
        self.policies = [ZeroFlowPolicy() if p is None else as_flow_policy(p) for p in policies]
        self.how = how
        self.input_key = getattr(first, "input_key", "count_image")
        self.voxel_bins = getattr(first, "voxel_bins", 5)
        self.device = "cpu"
        self.picked = [0] * len(policies)

    def reset(self, mask=None) -> None:
        for policy in self.policies:
            policy.reset()

    def act(self, obs, window: Window | None = None) -> np.ndarray:
        """The combined flow (``agents.policy.FlowPolicy``); "pick" needs the window."""
        if self.how == "pick" and window is None:
            raise ValueError("CombinedPolicy('pick') scores the flows on the window's events: call act(obs, window)")
        flows = [policy.act(obs, window) for policy in self.policies]
        if self.how == "avg":
            return np.mean(flows, axis=0).astype(np.float32)
        if len(window.events) == 0:
            return flows[0]
        size = flows[0].shape[-2:]
        batch = window.batch()
        with torch.no_grad():
            losses = [float(window_loss(torch.as_tensor(f)[None], batch, flow_scaling=float(max(size))).loss)
                      for f in flows]
        best = int(np.argmin(losses))
        self.picked[best] += 1
        return flows[best]
