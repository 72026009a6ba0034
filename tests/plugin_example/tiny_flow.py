"""A tiny recurrent flow model written the way a user would, against the protocol only.

Use it anywhere a model name is accepted: ``--model plugin_example.tiny_flow:build`` (with
``tests/`` on PYTHONPATH), or ``agents.make_model("plugin_example.tiny_flow:build")``.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn


class TinyFlow(nn.Module):
    """Two conv layers and an exponential moving average of the input as memory.

    forward(x (B, C, H, W), state) -> ([flow at 1/2, flow at full], {"memory": (B, C, H, W)}).
    Flows are tanh * flow_scaling pixels (full-resolution units at both scales). A zero memory
    is a fresh sequence, as the protocol requires.
    """

    def __init__(self, in_channels: int = 2, hidden: int = 6, flow_scaling: float = 128.0):
        super().__init__()
        self.in_channels = in_channels
        self.flow_scaling = flow_scaling
        self.body = nn.Conv2d(2 * in_channels, hidden, 3, padding=1)
        self.head = nn.Conv2d(hidden, 2, 3, padding=1)
        self.decay = nn.Parameter(torch.tensor(0.0))

    def forward(self, x, state=None):
        memory = torch.zeros_like(x) if state is None else state["memory"]
        memory = torch.sigmoid(self.decay) * memory + x
        flow = torch.tanh(self.head(F.relu(self.body(torch.cat([x, memory], dim=1)))))
        flow = flow * self.flow_scaling
        coarse = F.avg_pool2d(flow, 2, ceil_mode=True)
        return [coarse, flow], {"memory": memory}


def build(in_channels: int = 2, flow_scaling: float = 128.0, hidden: int = 6) -> TinyFlow:
    """Factory named on the command line. It takes no ``base_width``: make_model drops it."""
    return TinyFlow(in_channels=in_channels, hidden=hidden, flow_scaling=flow_scaling)
