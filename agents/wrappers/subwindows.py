"""Long windows as a chain of short ones: the network steps through N equal sub-windows of each
window and their flows are composed into the window's flow.

A recurrent network trained mostly on one-frame windows sees a four-frame window as a blur of
four frames of motion, up to four times further than anything it learned to follow. Stepped
through the window a frame at a time it does what it does best, with its recurrent state and
its prior flow carried from one sub-window to the next, and the window's flow is where each
pixel ends up after following the sub-window flows in turn::

    policy = SubWindowPolicy(RecurrentPolicy.from_pretrained(), splits=4)
    obs, info = env.reset()
    obs, reward, _, truncated, info = env.step(policy.act(obs, info["window"]))

The observation of each sub-window is built from its own events exactly as the env builds a
window's (``envs.representations``), so ``splits=1`` gives the wrapped policy's flow unchanged.
``scripts/evaluate.py --split N`` adds a row per model (``--split dt``: one sub-window per
ground-truth interval). Cost: N network steps per window.
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

from envs.representations import image_input
from envs.windows import Window

from ..policy import as_flow_policy

__all__ = ["SubWindowPolicy", "compose_flows", "sub_windows"]


def sub_windows(window: Window, splits: int) -> list[Window]:
    """``window`` (``info["window"]``) cut into ``splits`` windows of equal length (integer µs
    bounds), each ``[t_k, t_k+1)`` with its own events: :meth:`envs.windows.Window.split`."""
    return window.split(splits)


def compose_flows(flows) -> np.ndarray:
    """The displacement of each pixel after following ``flows`` in turn.

    flows: sequence of (2, H, W) flows (x then y, pixels), each over the sub-window after the
    previous one. A pixel at p moves to p + f1(p), then to that + f2(p + f1(p)), and so on; each
    flow is read bilinearly at the point's current position (clamped to the frame where a point
    has left it). Returns (2, H, W) float32: final position minus start.
    """
    flows = [torch.as_tensor(np.asarray(f, np.float32)) for f in flows]
    if not flows:
        raise ValueError("compose_flows needs at least one flow")
    total = flows[0].clone()
    height, width = total.shape[-2:]
    ys, xs = torch.meshgrid(torch.arange(height, dtype=torch.float32), torch.arange(width, dtype=torch.float32),
                            indexing="ij")
    for flow in flows[1:]:
        x = (xs + total[0]).clamp(0, width - 1)
        y = (ys + total[1]).clamp(0, height - 1)
        # grid_sample's normalised coordinates with align_corners=True: -1 and 1 are pixel centres 0 and N-1
        grid = torch.stack([2 * x / max(width - 1, 1) - 1, 2 * y / max(height - 1, 1) - 1], dim=-1)[None]
        total = total + F.grid_sample(flow[None], grid, mode="bilinear", padding_mode="border",
                                      align_corners=True)[0]
    return total.numpy().astype(np.float32)


class SubWindowPolicy:
    """A recurrent policy stepped through ``splits`` equal sub-windows of every window, its flows
    composed (:func:`compose_flows`) into the window's. The wrapped policy's state carries across
    sub-windows and windows alike; ``reset`` resets it. It acts on each sub-window's
    observation, given that sub-window (a :class:`~envs.windows.Window`) as its window."""

    def __init__(self, policy, splits: int) -> None:
        if int(splits) < 1:
            raise ValueError(f"splits must be >= 1, got {splits}")
        self.policy = as_flow_policy(policy)
        self.splits = int(splits)
        self.input_key = policy.input_key
        self.voxel_bins = getattr(policy, "voxel_bins", 5)
        self.device = getattr(policy, "device", "cpu")

    def reset(self, mask=None) -> None:
        self.policy.reset(mask)

    def observation(self, window: Window, size: tuple[int, int]) -> dict:
        """The wrapped policy's input for one (sub-)window, as the env builds it."""
        return {self.input_key: image_input(self.input_key, window.events, window.t_start, window.t_end,
                                            size, self.voxel_bins)}

    def act(self, obs, window: Window | None = None) -> np.ndarray:
        """The window's flow (``agents.policy.FlowPolicy``); with ``splits > 1`` it needs the
        window (its events)."""
        if self.splits == 1:
            return self.policy.act(obs, window)
        if window is None:
            raise ValueError(f"SubWindowPolicy with {self.splits} sub-windows cuts the window's events: "
                             "call act(obs, window)")
        size = tuple(np.asarray(obs[self.input_key]).shape[-2:])
        flows = [self.policy.act(self.observation(part, size), part) for part in sub_windows(window, self.splits)]
        return compose_flows(flows)
