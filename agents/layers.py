"""Building blocks of the flow networks (REFERENCE section 4).

All convolutions are 3x3 with "same" padding unless stated. Every recurrent layer takes its
previous hidden state as a tensor or ``None``; ``None`` and an all-zeros tensor mean the same
thing, a fresh sequence ("zero state at sequence start"), which is what lets the policy wrapper
reset single batch elements by zeroing their state.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn


def conv3x3(in_channels: int, out_channels: int, stride: int = 1, bias: bool = True) -> nn.Conv2d:
    return nn.Conv2d(in_channels, out_channels, 3, stride=stride, padding=1, bias=bias)


class ConvDown(nn.Module):
    """``conv_down(x) = relu(conv2d_stride2(x))``: halves the resolution."""

    def __init__(self, in_channels: int, out_channels: int):
        super().__init__()
        self.conv = conv3x3(in_channels, out_channels, stride=2)

    def forward(self, x: Tensor) -> Tensor:
        return F.relu(self.conv(x))


class ConvUp(nn.Module):
    """``conv_up(x) = relu(conv2d(upsample_bilinear(x)))``, x2 or to a given ``size``."""

    def __init__(self, in_channels: int, out_channels: int):
        super().__init__()
        self.conv = conv3x3(in_channels, out_channels)

    def forward(self, x: Tensor, size: tuple[int, int] | None = None) -> Tensor:
        if size is None:
            size = (2 * x.shape[-2], 2 * x.shape[-1])
        x = F.interpolate(x, size=size, mode="bilinear", align_corners=False)
        return F.relu(self.conv(x))


class ResidualBlock(nn.Module):
    """``RB(x) = relu(conv(relu(conv(x))) + x)`` (FERE-Net residual module, eq. 8)."""

    def __init__(self, channels: int):
        super().__init__()
        self.conv1 = conv3x3(channels, channels)
        self.conv2 = conv3x3(channels, channels)

    def forward(self, x: Tensor) -> Tensor:
        return F.relu(self.conv2(F.relu(self.conv1(x))) + x)


class ConvGRU(nn.Module):
    """Convolutional GRU, paper eq. 4.

    ``r = sig(Wxr*X + Whr*H)``, ``z = sig(Wxz*X + Whz*H)``,
    ``Hhat = tanh(r . (Whh*H) + Wxh*X)``, ``H' = (1 - z) . H + z . Hhat``.

    The three input-side convolutions are one conv with 3*hidden outputs (``x_convs``), the three
    hidden-side ones another (``h_convs``, no bias: the biases sit on the input side, so that
    ``r`` gates exactly ``Whh*H`` as eq. 4 writes it).

    Args:
        x: (B, C_in, h, w) input.
        hidden: (B, C_hidden, h, w) previous hidden state, or None for a fresh sequence (zeros).
    Returns:
        (B, C_hidden, h, w) new hidden state.
    """

    def __init__(self, input_size: int, hidden_size: int, kernel_size: int = 3):
        super().__init__()
        self.hidden_size = hidden_size
        padding = kernel_size // 2
        self.x_convs = nn.Conv2d(input_size, 3 * hidden_size, kernel_size, padding=padding)
        self.h_convs = nn.Conv2d(hidden_size, 3 * hidden_size, kernel_size, padding=padding, bias=False)

    def forward(self, x: Tensor, hidden: Tensor | None) -> Tensor:
        return self.step(self.x_convs(x), hidden)

    def step(self, x_proj: Tensor, hidden: Tensor | None) -> Tensor:
        """The update given the input side already convolved: ``x_proj = x_convs(x)``,
        (B, 3 * C_hidden, h, w) = [Wxr*X, Wxz*X, Wxh*X]."""
        n = self.hidden_size
        if hidden is None:
            # Zero state: Whh*0 = 0 (no hidden-side bias), so skip the conv but run the same
            # arithmetic as for a zeroed state: results are bitwise identical.
            hidden = x_proj.new_zeros(x_proj.shape[0], n, *x_proj.shape[2:])
            h_proj = torch.zeros_like(x_proj)
        else:
            h_proj = self.h_convs(hidden)
        gates = torch.sigmoid(x_proj[:, : 2 * n] + h_proj[:, : 2 * n])  # eq. 4, r and z
        r, z = gates[:, :n], gates[:, n:]
        candidate = torch.tanh(torch.addcmul(x_proj[:, 2 * n :], r, h_proj[:, 2 * n :]))  # eq. 4, Hhat
        return torch.addcmul(hidden, z, candidate - hidden)  # eq. 4, (1 - z) . H + z . Hhat


class STConvGRU(nn.Module):
    """Spatio-temporal ConvGRU of FERE-Net's first module (paper eqs. 5-6).

    Two memories: its own ``S`` (carried between windows) and ``M``, the deepest encoder's
    previous hidden state brought up to this module's resolution (built by the caller).

    ``S_k = ConvGRU_a(X, S_{k-1})``; ``Mbar_k = ConvGRU_b(X, M_{k-1})``;
    ``o_k = sig(Wfo*X + Wso*S_k + Wmo*Mbar_k)``; ``F_k = o_k . tanh(W_1x1 * [Mbar_k, S_k])``.

    Args:
        x: (B, C, h, w) input ``X``.
        own_memory: (B, C, h, w) ``S_{k-1}`` or None (fresh).
        deep_memory: (B, C, h, w) ``M_{k-1}`` or None (fresh).
    Returns:
        (output ``F_k``, new own memory ``S_k``), both (B, C, h, w).
    """

    def __init__(self, channels: int):
        super().__init__()
        self.gru_own = ConvGRU(channels, channels)  # ConvGRU_a, eq. 5
        self.gru_deep = ConvGRU(channels, channels)  # ConvGRU_b, eq. 5 (the M path)
        # o_k (eq. 6): Wfo*X (with the bias) + [Wmo, Wso] * [Mbar_k, S_k].
        self.gate_input = conv3x3(channels, channels)
        self.gate_hidden = conv3x3(2 * channels, channels, bias=False)
        # Wmm, Wss fused as one 1x1 conv over [Mbar_k, S_k] (eq. 6).
        self.fusion = nn.Conv2d(2 * channels, channels, 1)

    def forward(
        self, x: Tensor, own_memory: Tensor | None, deep_memory: Tensor | None
    ) -> tuple[Tensor, Tensor]:
        # Both GRUs' input sides in one call (same X, one pass); Wfo*X apart: with oneDNN on
        # CPU, 6 x hidden output channels in one conv run faster than 7 (at CPU width, 16 -> 96
        # plus 16 -> 16 took ~14 ms against ~20 ms for 16 -> 112, 128x128 batch 8, one thread).
        input_convs = [self.gru_own.x_convs, self.gru_deep.x_convs]
        weight = torch.cat([conv.weight for conv in input_convs])
        bias = torch.cat([conv.bias for conv in input_convs])
        projections = F.conv2d(x, weight, bias, padding=1)
        n = 3 * self.gru_own.hidden_size
        own = self.gru_own.step(projections[:, :n], own_memory)  # eq. 5, S_k
        deep = self.gru_deep.step(projections[:, n : 2 * n], deep_memory)  # eq. 5, Mbar_k
        memories = torch.cat([deep, own], dim=1)
        gate = torch.sigmoid(self.gate_input(x) + self.gate_hidden(memories))  # eq. 6, o_k
        out = gate * torch.tanh(self.fusion(memories))  # eq. 6, F_k
        return out, own
