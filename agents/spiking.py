"""Spiking neurons for XLIF-EV-FlowNet (REFERENCE section 4, Hagenaars et al. 2021).

A ConvXLIF layer is a strided convolution feeding leaky integrate-and-fire neurons with a soft
reset, whose firing threshold ``t0 + t1 * pt`` adapts to a presynaptic trace ``pt`` (a decaying
mean of |input| over each neuron's receptive field). The spike is a Heaviside step in the forward
pass and an arctan surrogate in the backward pass.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn


class ArctanSpike(torch.autograd.Function):
    """Heaviside spike ``(v > 0)`` with the arctan surrogate gradient.

    Backward uses ``d/dv [arctan(width * v) / width] = 1 / (1 + (width * v)^2)``: peak 1 at the
    threshold, width ``1 / width`` around it.
    """

    @staticmethod
    def forward(ctx, v: Tensor, width: float) -> Tensor:  # type: ignore[override]
        ctx.save_for_backward(v)
        ctx.width = width
        return (v > 0).to(v.dtype)

    @staticmethod
    def backward(ctx, grad_output: Tensor):  # type: ignore[override]
        (v,) = ctx.saved_tensors
        return grad_output / (1.0 + (ctx.width * v) ** 2), None


def arctan_spike(v: Tensor, width: float = 10.0) -> Tensor:
    return ArctanSpike.apply(v, width)


class ConvXLIF(nn.Module):
    """Convolutional adaptive-threshold LIF layer (stride 2: an encoder module).

    Per window k, with ``ff = conv(x)`` (no bias), per-channel leak ``a = sig(leak)`` and trace
    leak ``b = sig(trace_leak)``:

    - ``pt_k = b . pt_{k-1} + (1 - b) . avgpool_3x3(mean_c |x|)``  (presynaptic trace)
    - ``theta_k = t0 + t1 . pt_k``                               (adaptive threshold)
    - ``v_k = a . v_{k-1} + (1 - a) . ff - z_{k-1} . theta_k``      (soft reset)
    - ``z_k = H(v_k - theta_k)``                                   (spike, arctan surrogate)

    t0, t1 are per-channel and learnable (init 0.01 and 1.8); leaks init N(-4, 0.1) as in
    Hagenaars' code. State: ``(v, z, pt)``; all zeros is a fresh sequence.

    Args:
        x: (B, C_in, h, w) input (counts or spikes).
        state: tuple (v (B, C, h/2, w/2), z (B, C, h/2, w/2), pt (B, 1, h/2, w/2)) or None.
    Returns:
        (spikes z_k (B, C, h/2, w/2) in {0, 1}, new state tuple).
    """

    def __init__(
        self,
        in_channels: int,
        out_channels: int,
        t0: float = 0.01,
        t1: float = 1.8,
        leak_init: tuple[float, float] = (-4.0, 0.1),
        surrogate_width: float = 10.0,
    ):
        super().__init__()
        self.ff = nn.Conv2d(in_channels, out_channels, 3, stride=2, padding=1, bias=False)
        self.pool = nn.AvgPool2d(3, stride=2, padding=1)
        self.leak = nn.Parameter(torch.randn(1, out_channels, 1, 1) * leak_init[1] + leak_init[0])
        self.trace_leak = nn.Parameter(torch.randn(1, 1, 1, 1) * leak_init[1] + leak_init[0])
        self.t0 = nn.Parameter(torch.full((1, out_channels, 1, 1), t0))
        self.t1 = nn.Parameter(torch.full((1, out_channels, 1, 1), t1))
        self.surrogate_width = surrogate_width

    def forward(
        self, x: Tensor, state: tuple[Tensor, Tensor, Tensor] | None
    ) -> tuple[Tensor, tuple[Tensor, Tensor, Tensor]]:
        ff = self.ff(x)
        a = torch.sigmoid(self.leak)
        b = torch.sigmoid(self.trace_leak)
        trace_input = self.pool(x.abs().mean(dim=1, keepdim=True))
        if state is None:  # fresh sequence: zeros, with the same arithmetic as a zeroed state
            state = (torch.zeros_like(ff), torch.zeros_like(ff), torch.zeros_like(trace_input))
        v_prev, z_prev, pt_prev = state
        pt = b * pt_prev + (1 - b) * trace_input
        threshold = self.t0 + self.t1 * pt
        v = a * v_prev + (1 - a) * ff - z_prev * threshold
        z = arctan_spike(v - threshold, self.surrogate_width)
        return z, (v, z, pt)
