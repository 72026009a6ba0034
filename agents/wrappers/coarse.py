"""A network on a coarser sensor grid: each window's events binned ``factor`` x ``factor`` pixels
to one, the flow upsampled back: ``factor``^2 times fewer pixels to step through, and ``factor``
times the output range in sensor pixels (``tools/cheap_modes.py``, ``coarse:F``)::

    policy = CoarsePolicy(RecurrentPolicy.from_pretrained(), factor=2)
    obs, reward, _, truncated, info = env.step(policy.act(obs, info["window"]))
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

from envs.representations import image_input
from envs.windows import Window

from .subwindows import SubWindowPolicy, compose_flows, sub_windows

__all__ = ["CoarsePolicy"]


class CoarsePolicy(SubWindowPolicy):
    """The wrapped policy on the window's events binned ``factor`` x ``factor``: its input divided
    by ``factor``^2 (a block holds what one pixel did), its flow upsampled bilinearly to the sensor
    and multiplied by ``factor`` (pixels of the coarse grid to sensor pixels). With ``splits``, it
    steps through that many sub-windows of each window, their flows composed
    (:class:`~agents.wrappers.subwindows.SubWindowPolicy`)."""

    def __init__(self, policy, factor: int, splits: int = 1) -> None:
        super().__init__(policy, splits)
        if int(factor) < 1:
            raise ValueError(f"factor must be >= 1, got {factor}")
        self.factor = int(factor)

    def act(self, obs, window: Window | None = None) -> np.ndarray:
        """The window's flow (``agents.policy.FlowPolicy``), from its events binned coarser."""
        if window is None:
            raise ValueError("CoarsePolicy bins the window's events: call act(obs, window)")
        height, width = np.asarray(obs[self.input_key]).shape[-2:]
        f = self.factor
        size = (-(-height // f), -(-width // f))
        flows = []
        for part in sub_windows(window, self.splits):
            binned = part.bin(f)
            image = image_input(self.input_key, binned.events, binned.t_start, binned.t_end, size,
                                self.voxel_bins) / float(f * f)
            flows.append(self.policy.act({self.input_key: image}, binned))
        flow = torch.as_tensor(compose_flows(flows))[None]
        up = F.interpolate(flow, size=(size[0] * f, size[1] * f), mode="bilinear", align_corners=False)
        return (up[0, :, :height, :width] * f).numpy()
