"""The skeleton shared by every built-in flow network: pad, encode, residual, decode, crop.

Each network is a pure module honouring the policy protocol (see ``agents/protocol.py``):
``forward(x, state) -> (flows, state)``. Subclasses only say how they encode (and what state
their encoder carries); the residual module, the decoder with its skips, the tanh heads, the
flow scaling and the padding are here.

Widths follow the Hagenaars ConvGRU-EV-FlowNet family: base width ``c`` gives encoder outputs
2c/4c/8c/16c at 1/2, 1/4, 1/8, 1/16 resolution and decoder outputs 8c/4c/2c/c at 1/8, 1/4, 1/2, 1.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from losses import cpu_kernels_enabled, forward_warp_flow

from .layers import ConvGRU, ConvUp, ResidualBlock, is_channels_last, refine_flow

#: How a network may scale its input before encoding it (:func:`normalise_input`).
INPUT_NORMS = ("none", "nonzero-rms")

#: Named base widths: the paper's size and a size that trains on a laptop CPU.
WIDTHS: dict[str, int] = {"paper": 32, "cpu": 8}

#: Input sides are padded up to a multiple of this (four stride-2 encoders).
PAD_MULTIPLE = 16

NUM_SCALES = 4

State = dict[str, Tensor]


def resolve_base_width(base_width: int | None, width: str) -> int:
    """``base_width`` if given, else the named preset ``width`` ("paper" = 32, "cpu" = 8)."""
    if base_width is not None:
        if int(base_width) < 1:
            raise ValueError(f"base_width must be positive, got {base_width}")
        return int(base_width)
    if width not in WIDTHS:
        raise ValueError(f"unknown width preset {width!r}; expected one of {sorted(WIDTHS)}")
    return WIDTHS[width]


def pad_to_multiple(x: Tensor, multiple: int = PAD_MULTIPLE) -> Tensor:
    """Zero-pad the bottom and right of (B, C, H, W) so H and W are multiples of ``multiple``."""
    height, width = x.shape[-2:]
    pad_h = -height % multiple
    pad_w = -width % multiple
    if pad_h == 0 and pad_w == 0:
        return x
    return F.pad(x, (0, pad_w, 0, pad_h))


def normalise_input(x: Tensor, mode: str = "none") -> Tensor:
    """The network input scaled per sample: ``"none"`` returns ``x``; ``"nonzero-rms"`` divides
    each sample (all channels) by the root mean square of its nonzero entries, so that the
    pixels an event touched read about 1 whatever the recording's events per pixel, and a
    pixel without events stays 0 (a sample without events is returned unchanged)."""
    if mode == "none":
        return x
    if mode != "nonzero-rms":
        raise ValueError(f"unknown input normalisation {mode!r}; expected one of {INPUT_NORMS}")
    flat = x.reshape(x.shape[0], -1)
    count = (flat != 0).sum(dim=1).clamp(min=1).to(x.dtype)
    rms = torch.sqrt(flat.square().sum(dim=1) / count)
    rms = torch.where(rms > 0, rms, torch.ones_like(rms))
    return x / rms.view(-1, 1, 1, 1)


class FlowDecoder(nn.Module):
    """EV-FlowNet / FGD-Net decoder (eqs. 10-11): 4 modules with skips, tanh flow heads.

    ``D1 = conv_up(R ++ F4)``; ``D_l = conv_up(D_{l-1} ++ F_{5-l} ++ u_{l-1})`` for l > 1;
    ``uhat_l = tanh(conv(D_l))``; with ``refine`` (FGD-Net), ``u_l = ConvGRU_flow(uhat_l, ubar_l)``
    where ``ubar_l`` is the aligned prior flow downsampled to D_l's resolution, else ``u_l = uhat_l``.

    Options for the published baselines (defaults: EV-MGRFlowNet's decoder): ``head_kernel``, the
    flow heads' kernel (3, or 1 as in EV-FlowNet and Hagenaars' networks); ``upsample``, the
    class of the four upsampling convolutions (``ConvUp``: bilinear, zero padding).

    Args (forward):
        residual: (B, 16c, H/16, W/16) output R of the residual module.
        skips: [F1, F2, F3, F4], (B, 2^l c, H/2^l, W/2^l).
        prior: (B, 2, H, W) aligned prior flow in network units (pixels / flow_scaling), or None
            for a fresh sequence (zeros). Ignored without ``refine``.
    Returns:
        [u1, u2, u3, u4] at 1/8, 1/4, 1/2, 1 resolution, (B, 2, h, w), network units in [-1, 1].
    """

    def __init__(self, base_width: int, refine: bool, head_kernel: int = 3, upsample: type[nn.Module] = ConvUp):
        super().__init__()
        c = base_width
        skip_channels = [16 * c, 8 * c, 4 * c, 2 * c]  # F4, F3, F2, F1
        out_channels = [8 * c, 4 * c, 2 * c, c]
        in_channels = [16 * c + skip_channels[0]] + [
            out_channels[i - 1] + skip_channels[i] + 2 for i in range(1, NUM_SCALES)
        ]
        self.upsamples = nn.ModuleList(upsample(i, o) for i, o in zip(in_channels, out_channels))
        self.heads = nn.ModuleList(
            nn.Conv2d(o, 2, head_kernel, padding=head_kernel // 2) for o in out_channels
        )
        # ConvGRU_flow of each scale (eq. 11): input = fresh estimate, hidden = prior flow.
        self.refiners = nn.ModuleList(ConvGRU(2, 2) for _ in out_channels) if refine else None

    def forward(self, residual: Tensor, skips: list[Tensor], prior: Tensor | None) -> list[Tensor]:
        flows: list[Tensor] = []
        channels_last = is_channels_last(residual)
        x = residual
        if self.refiners is not None and prior is not None:
            priors = [prior]  # full, 1/2, 1/4, 1/8: 2x2 means of 2x2 means = block means
            for _ in range(NUM_SCALES - 1):
                priors.append(F.avg_pool2d(priors[-1], 2))
        for level in range(NUM_SCALES):
            parts = [x, skips[NUM_SCALES - 1 - level]]  # skip F_{5-l}
            if flows:
                # u_{l-1}, before the upsampling conv (the refiner's output may be NCHW)
                parts.append(flows[-1].contiguous(memory_format=torch.channels_last) if channels_last else flows[-1])
            x = self.upsamples[level](torch.cat(parts, dim=1))  # eq. 10, D_l
            head = self.heads[level](x)
            if self.refiners is None:
                flow = torch.tanh(head)  # eq. 10, u_l = uhat_l
            else:
                prior_here = None if prior is None else priors[NUM_SCALES - 1 - level]  # ubar_l
                flow = refine_flow(self.refiners[level], head, prior_here)  # eqs. 10-11, u_l
            flows.append(flow)
        return flows


class FlowNetBase(nn.Module):
    """Encoder -> residual module -> decoder, with padding, cropping and flow scaling.

    Subclasses implement :meth:`encode`; networks whose residual module or decoder differ from
    EV-MGRFlowNet's pass their own (``residual``, ``decoder``) and, if those carry state,
    override :meth:`bottleneck` and :meth:`decode`. ``forward(x, state) -> (flows, state)``:

    - x: (B, in_channels, H, W) float32 event count image (any H, W; padded to multiples of 16
      internally and cropped back).
    - state: None (fresh sequence) or the dict returned by the previous call; an all-zeros entry
      is exactly a fresh sequence for that batch element.
    - flows: 4 tensors (B, 2, ceil(H/s), ceil(W/s)) for s = 8, 4, 2, 1 (finest last), pixels of
      displacement over the window in full-resolution units, within +-flow_scaling.

    Memory layout: on CPU the activations (and so the recurrent state) are channels-last tensors,
    in which oneDNN's convolutions run faster than in NCHW at these widths (the whole network
    1.4-2.2x at CPU width, README benchmarks) and the recurrent layers' gate arithmetic runs in
    compiled kernels (``agents/_kernels.py``); the returned flows are always contiguous NCHW. ``channels_last = False`` keeps NCHW inside (the
    torch reference path); ``True`` forces channels-last on any device; ``None`` (default) means
    channels-last on CPU only, unless the compiled CPU kernels are switched off
    (``losses.cpu_kernels(False)``, ``EVFLOW_CPU_KERNELS=0``): then NCHW, the path CUDA takes.
    Values do not depend on it beyond float rounding.
    """

    channels_last: bool | None = None

    def __init__(
        self,
        in_channels: int,
        base_width: int,
        flow_scaling: float,
        use_prior_flow: bool,
        residual: nn.Module | None = None,
        decoder: nn.Module | None = None,
        input_norm: str = "none",
    ):
        super().__init__()
        if input_norm not in INPUT_NORMS:
            raise ValueError(f"unknown input_norm {input_norm!r}; expected one of {INPUT_NORMS}")
        self.input_norm = input_norm
        self.in_channels = int(in_channels)
        self.base_width = int(base_width)
        self.flow_scaling = float(flow_scaling)
        self.use_prior_flow = bool(use_prior_flow)
        deepest = 16 * self.base_width
        # Residual module (eq. 8): R = RB2(RB1(F4)).
        if residual is None:
            residual = nn.Sequential(ResidualBlock(deepest), ResidualBlock(deepest))
        self.residual = residual
        self.decoder = decoder if decoder is not None else FlowDecoder(self.base_width, refine=self.use_prior_flow)
        self.config: dict = {}

    def _use_channels_last(self, x: Tensor) -> bool:
        if self.channels_last is None:  # CUDA's path (NCHW) when the CPU kernels are switched off
            return x.device.type == "cpu" and cpu_kernels_enabled()
        return bool(self.channels_last)

    def encode(self, x: Tensor, state: State, new_state: State) -> list[Tensor]:
        """Return the skips [F1, F2, F3, F4]; read previous state, write the new one."""
        raise NotImplementedError

    def bottleneck(self, deepest: Tensor, state: State, new_state: State) -> Tensor:
        """The residual module on the deepest skip F4 (stateless unless overridden)."""
        return self.residual(deepest)

    def decode(self, residual: Tensor, skips: list[Tensor], prior: Tensor | None, state: State,
               new_state: State) -> list[Tensor]:
        """The four scales' flows in network units (stateless unless overridden)."""
        return self.decoder(residual, skips, prior)

    def forward(self, x: Tensor, state: State | None = None) -> tuple[list[Tensor], State]:
        if x.dim() != 4 or x.shape[1] != self.in_channels:
            raise ValueError(
                f"expected input (B, {self.in_channels}, H, W), got {tuple(x.shape)}"
            )
        state = {} if state is None else state
        height, width = x.shape[-2:]
        padded = pad_to_multiple(normalise_input(x, self.input_norm))
        layout = torch.channels_last if self._use_channels_last(x) else torch.contiguous_format
        padded = padded.contiguous(memory_format=layout)
        new_state: State = {}
        skips = self.encode(padded, state, new_state)
        residual = self.bottleneck(skips[-1], state, new_state)

        prior = None
        previous_flow = state.get("prior_flow") if self.use_prior_flow else None
        if previous_flow is not None:
            aligned = forward_warp_flow(previous_flow)  # eq. 9, ubar_k in pixels
            prior = pad_to_multiple(aligned / self.flow_scaling)  # back to network units

        flows = []
        for scale_flow in self.decode(residual, skips, prior, state, new_state):
            stride = padded.shape[-1] // scale_flow.shape[-1]
            cropped = scale_flow[..., : math.ceil(height / stride), : math.ceil(width / stride)]
            flows.append((cropped * self.flow_scaling).contiguous())  # NCHW, whatever the layout inside
        if self.use_prior_flow:
            new_state["prior_flow"] = flows[-1]
        return flows, new_state
