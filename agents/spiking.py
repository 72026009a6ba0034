"""Spiking neurons for XLIF-EV-FlowNet (docs/method.md, "Network", Hagenaars et al. 2021).

A ConvXLIF layer is a strided convolution feeding leaky integrate-and-fire neurons with a soft
reset, whose firing threshold ``t0 + t1 * pt`` adapts to a presynaptic trace ``pt`` (a decaying
mean of |input| over each neuron's receptive field). The spike is a Heaviside step in the forward
pass and an arctan surrogate in the backward pass.
"""

from __future__ import annotations

import torch
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


# -- Hagenaars et al.'s XLIF neurons, as the authors describe them (XLIF-EV-FlowNet) ------------


class ArctanSurrogateSpike(torch.autograd.Function):
    """Heaviside spike ``(x > 0)`` whose backward is the arctan-derivative surrogate in the form
    Hagenaars et al. use: ``dz/dx = 1 / (1 + width . x^2)`` (width 10: peak 1 at the threshold,
    half height at |x| = 1 / sqrt(width)). Note the width multiplies x^2, not (width . x)^2 as
    in :class:`ArctanSpike`: the two classes differ only in that line of ``backward``, kept
    apart so that each surrogate reads as its paper writes it."""

    @staticmethod
    def forward(ctx, x: Tensor, width: float) -> Tensor:  # type: ignore[override]
        ctx.save_for_backward(x)
        ctx.width = width
        return (x > 0).to(x.dtype)

    @staticmethod
    def backward(ctx, grad_output: Tensor):  # type: ignore[override]
        (x,) = ctx.saved_tensors
        return grad_output / (1.0 + ctx.width * x * x), None


def arctan_surrogate_spike(x: Tensor, width: float = 10.0) -> Tensor:
    return ArctanSurrogateSpike.apply(x, width)


XLIFState = tuple[Tensor, Tensor, Tensor]


class XLIFLayer(nn.Module):
    """A convolution feeding XLIF neurons (Hagenaars et al. 2021): leaky integrate-and-fire
    with a soft reset and a threshold that adapts to a presynaptic trace, all per channel.

    With ``I = W * x`` (no bias; plus ``R * z_{k-1}`` for a recurrent layer), per channel c
    ``a = sig(leak_v)``, ``b = sig(leak_pt)``, ``theta(pt) = t0 + t1 . pt`` with t0 clamped to
    >= 0.01 and t1 to >= 0:

    - ``pt_k = b . pt_{k-1} + (1 - b) . avgpool(mean over input channels of |x|)``  (trace)
    - ``v_k = a . v_{k-1} + (1 - a) . I - sg(z_{k-1}) . theta(pt_{k-1})``
      (soft reset by the previous step's threshold, the spike detached: sg = stop-gradient)
    - ``z_k = H(v_k - theta(pt_k))`` with :func:`arctan_surrogate_spike`'s gradient.

    Initialisation as the authors': W ~ U(+-sqrt(1 / C_in)), R ~ U(+-sqrt(1 / C_out)),
    leak_v, leak_pt ~ N(-4, 0.1) per channel, t0 = 0.01, t1 = 1.8. ``learn_leak`` (default True)
    and ``learn_threshold`` (default False: t0, t1 are fixed buffers) choose what trains.

    Args (forward): x (B, C_in, h, w); state (v, z, pt), each (B, C_out, h', w'), or None (a
    fresh sequence: zeros); residual, added to the output spikes (a spiking residual block).
    Returns: (z_k + residual, (v_k, z_k, pt_k)); h' = ceil(h / stride).
    """

    def __init__(
        self,
        in_channels: int,
        out_channels: int,
        kernel_size: int = 3,
        stride: int = 1,
        recurrent: bool = False,
        learn_leak: bool = True,
        learn_threshold: bool = False,
        t0: float = 0.01,
        t1: float = 1.8,
        leak_init: tuple[float, float] = (-4.0, 0.1),
        surrogate_width: float = 10.0,
    ):
        super().__init__()
        padding = kernel_size // 2
        self.ff = nn.Conv2d(in_channels, out_channels, kernel_size, stride=stride, padding=padding, bias=False)
        nn.init.uniform_(self.ff.weight, -(1 / in_channels) ** 0.5, (1 / in_channels) ** 0.5)
        self.rec = None
        if recurrent:
            self.rec = nn.Conv2d(out_channels, out_channels, kernel_size, padding=padding, bias=False)
            nn.init.uniform_(self.rec.weight, -(1 / out_channels) ** 0.5, (1 / out_channels) ** 0.5)
        self.pool = nn.AvgPool2d(kernel_size, stride, padding=padding)
        shape = (1, out_channels, 1, 1)
        leaks = {name: torch.randn(shape) * leak_init[1] + leak_init[0] for name in ("leak_v", "leak_pt")}
        thresholds = {"t0": torch.full(shape, float(t0)), "t1": torch.full(shape, float(t1))}
        for group, learn in ((leaks, learn_leak), (thresholds, learn_threshold)):
            for name, value in group.items():
                if learn:
                    setattr(self, name, nn.Parameter(value))
                else:
                    self.register_buffer(name, value)
        self.surrogate_width = float(surrogate_width)

    def forward(self, x: Tensor, state: XLIFState | None, residual: Tensor | float = 0.0):
        current = self.ff(x)
        if state is None:
            state = (torch.zeros_like(current), torch.zeros_like(current), torch.zeros_like(current))
        v, z, pt = state
        if self.rec is not None:
            current = current + self.rec(z)
        t0, t1 = self.t0.clamp_min(0.01), self.t1.clamp_min(0.0)
        a, b = torch.sigmoid(self.leak_v), torch.sigmoid(self.leak_pt)
        pt_new = b * pt + (1 - b) * self.pool(x.abs().mean(dim=1, keepdim=True))
        v_new = a * v + (1 - a) * current - z.detach() * (t0 + t1 * pt)
        z_new = arctan_surrogate_spike(v_new - (t0 + t1 * pt_new), self.surrogate_width)
        return z_new + residual, (v_new, z_new, pt_new)
