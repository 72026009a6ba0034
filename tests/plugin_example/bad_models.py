"""Factories that break the protocol, each in one way (for the error-message tests)."""

from __future__ import annotations

import torch
from torch import nn


def not_a_module(**kwargs):
    return lambda x, state: ([x[:, :2]], {})


class WrongFlowShape(nn.Module):
    def forward(self, x, state=None):
        return [x[:, :1]], {}  # 1 channel instead of 2


class ZeroStateIsNotFresh(nn.Module):
    """Its fresh state is ones, not zeros: the policy could not reset it by zeroing."""

    def forward(self, x, state=None):
        memory = torch.ones_like(x[:, :1]) if state is None else state["memory"]
        return [x[:, :2] * memory], {"memory": memory * 0.5}


def wrong_flow_shape(**kwargs):
    return WrongFlowShape()


def zero_state_is_not_fresh(**kwargs):
    return ZeroStateIsNotFresh()


not_callable = 3
