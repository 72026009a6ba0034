"""EV-MGRFlowNet (Zhuang et al. 2024): FERE-Net encoder + FGD-Net decoder (docs/method.md, "Network").

FERE-Net: module 1 is an ST-ConvGRU (eqs. 5-6) whose second memory is the deepest encoder's
previous hidden state brought up to 1/2 resolution; modules 2-4 are conv_down + ConvGRU (eq. 7);
then the residual module (eq. 8). FGD-Net: the EV-FlowNet decoder whose every scale's estimate is
refined by a ConvGRU with the forward-warped (eq. 9), downsampled prior flow as hidden state
(eqs. 10-11).

State (all (B, ...) tensors, all zeros = fresh sequence):
    "encoder1".."encoder4": hidden states S_l, (B, 2^l c, Hp/2^l, Wp/2^l) (Hp, Wp: H, W padded
        up to multiples of 16);
    "prior_flow": (B, 2, H, W) the previous window's full-resolution flow, pixels
        (only with ``use_prior_flow``).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from .flownet import FlowNetBase, State, resolve_base_width
from .layers import ConvDown, ConvGRU, STConvGRU, conv3x3, is_channels_last


def _shifted_upsampling_matrices(n_in: int, n_out: int, like: Tensor) -> Tensor:
    """(3, n_out, n_in): bilinear (align_corners=False) 1-D upsampling matrix, rows shifted by
    -1, 0, +1 with zero fill, i.e. the three row taps of a 3x3 conv with zero padding."""
    eye = torch.eye(n_in, dtype=like.dtype, device=like.device).unsqueeze(0)
    upsample = F.interpolate(eye, size=n_out, mode="linear", align_corners=False)[0].T
    padded = F.pad(upsample, (0, 0, 1, 1))
    return torch.stack([padded[shift : shift + n_out] for shift in range(3)])


class DeepMemoryUp(nn.Module):
    """``M_{k-1} = conv_up(S4_{k-1}) = relu(conv3x3(upsample_bilinear(S4_{k-1}, size)))`` (eq. 5's
    second memory, brought from 1/16 up to module 1's 1/2 resolution).

    Computed exactly (up to float rounding) but without the 3x3 conv at 1/2 resolution, which
    alone cost about 10 % of the network's forward time at paper width: channel mixing and
    bilinear upsampling commute, so each of the 9 taps mixes channels at 1/16 resolution, and
    the upsampling + tap shift is applied as two small matrices per axis. The slow, obvious form
    is the oracle in ``tests/test_agents.py``.

    The conv has no bias so that ``S4 = 0`` (fresh sequence) gives ``M = 0`` exactly: both
    memories of the ST-ConvGRU start at zero, and a zeroed state is a fresh sequence.
    """

    def __init__(self, in_channels: int, out_channels: int):
        super().__init__()
        self.conv = conv3x3(in_channels, out_channels, bias=False)

    def forward(self, deepest_hidden: Tensor, size: tuple[int, int]) -> Tensor:
        """deepest_hidden: (B, C4, h, w) S4_{k-1}; returns (B, C1, *size) M_{k-1}, in the layout
        of ``deepest_hidden`` (channels-last or NCHW)."""
        batch, channels, height, width = deepest_hidden.shape
        channels_last = is_channels_last(deepest_hidden)
        weight = self.conv.weight  # (O, C, 3, 3)
        out_channels = weight.shape[0]
        tap_weights = weight.permute(2, 3, 0, 1).reshape(9 * out_channels, channels, 1, 1)
        taps = F.conv2d(deepest_hidden, tap_weights)  # each tap's channel mixing, low resolution
        taps = taps.view(batch, 3, 3, out_channels, height, width)
        rows = _shifted_upsampling_matrices(height, size[0], deepest_hidden)  # (3, H, h)
        cols = _shifted_upsampling_matrices(width, size[1], deepest_hidden)  # (3, W, w)
        if channels_last:
            # The row pass as one matrix product whose result is (B, H, W, O) in memory, i.e. the
            # channels-last (B, O, H, W) tensor itself, with no copy afterwards.
            half = torch.einsum("bijoyx,jXx->biyXo", taps, cols).contiguous()  # (B, 3, h, W, O)
            row_taps = rows.permute(1, 0, 2).reshape(size[0], 3 * height)  # (H, 3h)
            memory = torch.matmul(row_taps, half.view(batch, 3 * height, size[1] * out_channels))
            return F.relu(memory).view(batch, size[0], size[1], out_channels).permute(0, 3, 1, 2)
        half = torch.einsum("bijoyx,jXx->bioyX", taps, cols)
        return F.relu(torch.einsum("bioyX,iYy->boYX", half, rows))


class EVMGRFlowNet(FlowNetBase):
    """EV-MGRFlowNet. Switches for the paper's ablations.

    Args:
        in_channels: input channels (2 for the event count image, eq. 2).
        base_width: base width c (paper 32); None takes the ``width`` preset.
        width: "paper" (c = 32) or "cpu" (c = 8), used when ``base_width`` is None.
        flow_scaling: pixels per unit of tanh output (Hagenaars: 128, the training crop side).
        use_st_convgru: False = ablation "without ST-ConvGRU" (module 1 is a plain ConvGRU).
        use_prior_flow: False = ablation "without prior flows" (u_l = uhat_l).
        input_norm: "none" (the paper's input) or "nonzero-rms" (each window scaled by the root
            mean square of its nonzero entries: the flownet module's ``normalise_input``).
    """

    def __init__(
        self,
        in_channels: int = 2,
        base_width: int | None = None,
        width: str = "paper",
        flow_scaling: float = 128.0,
        use_st_convgru: bool = True,
        use_prior_flow: bool = True,
        input_norm: str = "none",
    ):
        c = resolve_base_width(base_width, width)
        super().__init__(in_channels, c, flow_scaling, use_prior_flow, input_norm=input_norm)
        self.use_st_convgru = bool(use_st_convgru)
        channels = [2 * c, 4 * c, 8 * c, 16 * c]
        inputs = [in_channels] + channels[:-1]
        self.downs = nn.ModuleList(ConvDown(i, o) for i, o in zip(inputs, channels))
        first = STConvGRU(channels[0]) if self.use_st_convgru else ConvGRU(channels[0], channels[0])
        self.grus = nn.ModuleList([first] + [ConvGRU(ch, ch) for ch in channels[1:]])
        self.deep_memory_up = DeepMemoryUp(channels[-1], channels[0]) if self.use_st_convgru else None
        self.config = {
            "in_channels": self.in_channels,
            "base_width": self.base_width,
            "flow_scaling": self.flow_scaling,
            "use_st_convgru": self.use_st_convgru,
            "use_prior_flow": self.use_prior_flow,
        }
        if self.input_norm != "none":  # older checkpoints' configs stay as they were
            self.config["input_norm"] = self.input_norm

    def encode(self, x: Tensor, state: State, new_state: State) -> list[Tensor]:
        skips = []
        for level, (down, gru) in enumerate(zip(self.downs, self.grus)):
            key = f"encoder{level + 1}"
            x = down(x)
            if level == 0 and self.deep_memory_up is not None:
                deepest = state.get("encoder4")
                memory = None if deepest is None else self.deep_memory_up(deepest, x.shape[-2:])
                x, new_state[key] = gru(x, state.get(key), memory)  # eqs. 5-6, F1 and S1
            else:
                x = new_state[key] = gru(x, state.get(key))  # eq. 7, F_l = S_l
            skips.append(x)
        return skips
