"""Baselines with EV-MGRFlowNet's interface (docs/method.md, "Network" and "Baselines").

The published networks, as their authors describe them (our code, written from the papers and
the facts of their public implementations):

- :class:`EVFlowNet` (Zhu et al., RSS 2018): 4-channel input (counts and latest timestamps per
  polarity, observation "count_time_image"), stride-2 encoders, EV-FlowNet residual blocks,
  nearest-neighbour upsampling with reflection padding, 1x1 tanh heads, variance-scaling init.
- :class:`ConvGRUEVFlowNet` (Hagenaars et al., NeurIPS 2021, "RecEVFlowNet"): every encoder a
  stride-2 conv + ReLU followed by their ConvGRU (reset applied to the hidden state before its
  convolution, orthogonal init), bilinear upsampling decoder, 1x1 tanh heads.
- :class:`XLIFEVFlowNet` (Hagenaars et al.): spiking throughout: XLIF encoders (a feed-forward
  and a recurrent spiking layer each), spiking residual blocks (spikes + input), spiking
  decoders, 1x1 tanh heads initialised in U(+-0.01).

And the project's earlier stand-ins, under names that say what they are: EV-MGRFlowNet's U-Net
(conv_down encoders, bilinear conv_up decoder, 3x3 tanh heads) with no recurrence
(:class:`UNetFeedforward`, "unet-feedforward"), with eq. 4 ConvGRU encoders
(:class:`UNetConvGRU`, "unet-convgru") or with spiking encoders only (:class:`UNetXLIFEncoder`,
"unet-xlif-encoder").

All share :class:`agents.flownet.FlowNetBase`: padding to a multiple of 16, four stride-2
encoders with outputs 2c/4c/8c/16c, decoder outputs 8c/4c/2c/c with the previous scale's flow
concatenated, flows at 1/8..1 in pixels (tanh x flow_scaling).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from .flownet import FlowDecoder, FlowNetBase, State, resolve_base_width
from .layers import ConvDown, ConvGRU, ConvUpNearestReflect, HagenaarsConvGRU, ZhuResidualBlock, zhu_init_
from .spiking import ConvXLIF, XLIFLayer

NUM_LEVELS = 4


def _channels(in_channels: int, c: int) -> tuple[list[int], list[int]]:
    outputs = [2 * c, 4 * c, 8 * c, 16 * c]
    return [in_channels] + outputs[:-1], outputs


class _Baseline(FlowNetBase):
    """Width resolution and ``config`` shared by the baselines (no ablation switches)."""

    def __init__(self, in_channels, base_width, width, flow_scaling, residual=None, decoder_kwargs=None):
        c = resolve_base_width(base_width, width)
        decoder = FlowDecoder(c, refine=False, **decoder_kwargs) if decoder_kwargs is not None else None
        super().__init__(in_channels, c, flow_scaling, use_prior_flow=False, residual=residual(c) if residual else None,
                         decoder=decoder)
        self.config = {"in_channels": self.in_channels, "base_width": self.base_width,
                       "flow_scaling": self.flow_scaling}


# The baselines' __init__ signatures repeat on purpose: make_model passes only the keyword
# arguments a factory's signature names.
def _add_recurrent_encoder(net: _Baseline, gru: type) -> None:
    """Four encoder levels ``F_l = gru_l(conv_down_l(F_{l-1}), F_l at k-1)`` (ConvGRU-EV-FlowNet
    with Hagenaars' GRU, UNetConvGRU with eq. 4's)."""
    inputs, outputs = _channels(net.in_channels, net.base_width)
    net.downs = nn.ModuleList(ConvDown(i, o) for i, o in zip(inputs, outputs))
    net.grus = nn.ModuleList(gru(o, o) for o in outputs)


def _recurrent_encode(self, x: Tensor, state: State, new_state: State) -> list[Tensor]:
    """The encoder of :func:`_add_recurrent_encoder`; state "encoder1".."encoder4"."""
    skips = []
    for level, (down, gru) in enumerate(zip(self.downs, self.grus)):
        key = f"encoder{level + 1}"
        x = new_state[key] = gru(down(x), state.get(key))
        skips.append(x)
    return skips


def _feedforward_encode(self, x: Tensor, state: State, new_state: State) -> list[Tensor]:
    """Four stateless encoder levels ``F_l = conv_down_l(F_{l-1})`` (``self.downs``)."""
    skips = []
    for down in self.downs:
        x = down(x)
        skips.append(x)
    return skips


# -- the published baselines ------------------------------------------------------------------


class EVFlowNet(_Baseline):
    """EV-FlowNet as Zhu et al. built it (stateless: the returned state is an empty dict).

    Input (default ``in_channels=4``): the observation "count_time_image", [ON counts, OFF
    counts, ON latest time, OFF latest time]; ``in_channels=2`` gives their count-only variant.
    Encoders ``F_l = relu(conv3x3_stride2(F_{l-1}))``; two residual blocks
    ``x + relu(conv(relu(conv(x))))`` (:class:`agents.layers.ZhuResidualBlock`); decoders
    ``D_l = relu(conv3x3_valid(reflect_pad(nearest_x2([D_{l-1}, F_{5-l}, u_{l-1}]))))``; heads
    ``u_l = tanh(conv1x1(D_l))``. Every convolution initialised as EV-FlowNet's code does
    (:func:`agents.layers.zhu_init_`). Zhu scales the tanh by 256 px; here by ``flow_scaling``.
    """

    def __init__(self, in_channels: int = 4, base_width: int | None = None, width: str = "paper",
                 flow_scaling: float = 128.0):
        super().__init__(in_channels, base_width, width, flow_scaling,
                         residual=lambda c: nn.Sequential(ZhuResidualBlock(16 * c), ZhuResidualBlock(16 * c)),
                         decoder_kwargs={"head_kernel": 1, "upsample": ConvUpNearestReflect})
        self.downs = nn.ModuleList(ConvDown(i, o) for i, o in zip(*_channels(self.in_channels, self.base_width)))
        for down in self.downs:
            zhu_init_(down.conv)
        for head in self.decoder.heads:
            zhu_init_(head)

    encode = _feedforward_encode


class ConvGRUEVFlowNet(_Baseline):
    """ConvGRU-EV-FlowNet as Hagenaars et al. built it ("RecEVFlowNet").

    Encoder l: ``F_l = GRU_l(relu(conv3x3_stride2(F_{l-1})), F_l at k-1)`` with
    :class:`agents.layers.HagenaarsConvGRU` (reset on the hidden state before its convolution,
    orthogonal weights, zero biases); residual blocks ``relu(conv(relu(conv(x))) + x)``;
    decoders ``D_l = relu(conv3x3(bilinear_x2([D_{l-1}, F_{5-l}, u_{l-1}])))``; heads
    ``u_l = tanh(conv1x1(D_l))``.

    State: "encoder1".."encoder4", hidden states (B, 2^l c, Hp/2^l, Wp/2^l).
    """

    def __init__(self, in_channels: int = 2, base_width: int | None = None, width: str = "paper",
                 flow_scaling: float = 128.0):
        super().__init__(in_channels, base_width, width, flow_scaling, decoder_kwargs={"head_kernel": 1})
        _add_recurrent_encoder(self, HagenaarsConvGRU)

    encode = _recurrent_encode


def _xlif_step(layer: XLIFLayer, key: str, x: Tensor, state: State, new_state: State, residual=0.0) -> Tensor:
    """Run one XLIF layer with its state stored as ``key_v``, ``key_z``, ``key_pt``."""
    previous = (state[f"{key}_v"], state[f"{key}_z"], state[f"{key}_pt"]) if f"{key}_v" in state else None
    out, (v, z, pt) = layer(x, previous, residual)
    new_state[f"{key}_v"], new_state[f"{key}_z"], new_state[f"{key}_pt"] = v, z, pt
    return out


class XLIFEVFlowNet(FlowNetBase):
    """XLIF-EV-FlowNet as Hagenaars et al. built it: spiking everywhere but the flow heads.

    Every spiking layer is an :class:`agents.spiking.XLIFLayer` (3x3, per-channel leaks through a
    sigmoid, fixed thresholds t0 = 0.01, t1 = 1.8 clamped to >= 0.01 and >= 0, soft reset by the
    previous threshold with the spike detached, arctan surrogate ``1 / (1 + 10 x^2)``).

    - encoder l: a feed-forward XLIF layer (stride 2) then a recurrent one (stride 1, its own
      spikes of the previous window through a second convolution): ``F_l`` are spikes;
    - residual module: two spiking residual blocks, ``out = z2 + x`` with
      ``z2 = XLIF(XLIF(x))`` (spikes plus the block's input);
    - decoder l: bilinear x2 of ``[D_{l-1}, F_{5-l}, u_{l-1}]``, then a feed-forward XLIF layer;
    - heads: ``u_l = tanh(conv1x1(D_l))``, weights U(-0.01, 0.01), biases 0 (near zero flow at
      the start, as the authors initialise their spiking networks' heads).

    State: ``{part}_v``, ``{part}_z``, ``{part}_pt`` for part in encoder{l}_ff, encoder{l}_rec,
    residual{i}_conv{1,2}, decoder{l}; each (B, C, h, w) of that layer's output.
    """

    def __init__(self, in_channels: int = 2, base_width: int | None = None, width: str = "paper",
                 flow_scaling: float = 128.0, learn_leak: bool = True, learn_threshold: bool = False):
        c = resolve_base_width(base_width, width)
        options = {"learn_leak": learn_leak, "learn_threshold": learn_threshold}
        # the residual module and decoder spike and carry state: see bottleneck() and decode()
        residual = nn.ModuleList(
            nn.ModuleList([XLIFLayer(16 * c, 16 * c, **options), XLIFLayer(16 * c, 16 * c, **options)])
            for _ in range(2)
        )
        super().__init__(in_channels, c, flow_scaling, use_prior_flow=False, residual=residual,
                         decoder=SpikingFlowDecoder(c, **options))
        self.config = {"in_channels": self.in_channels, "base_width": self.base_width,
                       "flow_scaling": self.flow_scaling, **options}
        inputs, outputs = _channels(self.in_channels, c)
        self.encoder_ff = nn.ModuleList(XLIFLayer(i, o, stride=2, **options) for i, o in zip(inputs, outputs))
        self.encoder_rec = nn.ModuleList(XLIFLayer(o, o, recurrent=True, **options) for o in outputs)

    def encode(self, x: Tensor, state: State, new_state: State) -> list[Tensor]:
        skips = []
        for level, (ff, rec) in enumerate(zip(self.encoder_ff, self.encoder_rec)):
            x = _xlif_step(ff, f"encoder{level + 1}_ff", x, state, new_state)
            x = _xlif_step(rec, f"encoder{level + 1}_rec", x, state, new_state)
            skips.append(x)
        return skips

    def bottleneck(self, deepest: Tensor, state: State, new_state: State) -> Tensor:
        x = deepest
        for i, (conv1, conv2) in enumerate(self.residual):
            spikes = _xlif_step(conv1, f"residual{i + 1}_conv1", x, state, new_state)
            x = _xlif_step(conv2, f"residual{i + 1}_conv2", spikes, state, new_state, residual=x)
        return x

    def decode(self, residual: Tensor, skips: list[Tensor], prior: Tensor | None, state: State,
               new_state: State) -> list[Tensor]:
        return self.decoder(residual, skips, state, new_state)


class SpikingFlowDecoder(nn.Module):
    """XLIF-EV-FlowNet's decoder: for l = 1..4, ``D_l = XLIF(bilinear_x2([D_{l-1}, F_{5-l},
    u_{l-1}]))`` (D_0 = R, no u_0) and ``u_l = tanh(conv1x1(D_l))`` with head weights
    U(-0.01, 0.01), biases 0. forward(residual, skips, state, new_state) -> [u1..u4], network
    units; layer l's state under "decoder{l}_v/_z/_pt"."""

    def __init__(self, base_width: int, **options):
        super().__init__()
        c = base_width
        skip_channels = [16 * c, 8 * c, 4 * c, 2 * c]
        out_channels = [8 * c, 4 * c, 2 * c, c]
        inputs = [32 * c] + [out_channels[i - 1] + skip_channels[i] + 2 for i in range(1, NUM_LEVELS)]
        self.layers = nn.ModuleList(XLIFLayer(i, o, **options) for i, o in zip(inputs, out_channels))
        self.heads = nn.ModuleList(nn.Conv2d(o, 2, 1) for o in out_channels)
        for head in self.heads:
            nn.init.uniform_(head.weight, -0.01, 0.01)
            nn.init.zeros_(head.bias)

    def forward(self, residual: Tensor, skips: list[Tensor], state: State, new_state: State) -> list[Tensor]:
        flows: list[Tensor] = []
        x = residual
        for level in range(NUM_LEVELS):
            parts = [x, skips[NUM_LEVELS - 1 - level]] + flows[-1:]
            up = F.interpolate(torch.cat(parts, dim=1), scale_factor=2, mode="bilinear", align_corners=False)
            x = _xlif_step(self.layers[level], f"decoder{level + 1}", up, state, new_state)
            flows.append(torch.tanh(self.heads[level](x)))
        return flows



# -- the project's earlier stand-ins, named for what they are -----------------------------------


class UNetFeedforward(_Baseline):
    """EV-MGRFlowNet's U-Net with no recurrence: encoders ``relu(conv3x3_stride2)``, residual
    blocks ``relu(conv(relu(conv(x))) + x)``, bilinear conv_up decoder, 3x3 tanh heads.
    Stateless: the returned state is an empty dict. Not Zhu's EV-FlowNet (see :class:`EVFlowNet`).
    """

    def __init__(self, in_channels: int = 2, base_width: int | None = None, width: str = "paper",
                 flow_scaling: float = 128.0):
        super().__init__(in_channels, base_width, width, flow_scaling)
        self.downs = nn.ModuleList(ConvDown(i, o) for i, o in zip(*_channels(self.in_channels, self.base_width)))

    encode = _feedforward_encode


class UNetConvGRU(_Baseline):
    """EV-MGRFlowNet's U-Net with every encoder conv_down + the eq. 4 ConvGRU (EV-MGRFlowNet
    with both ablation switches off has exactly this network). Not Hagenaars' ConvGRU-EV-FlowNet
    (see :class:`ConvGRUEVFlowNet`).

    State: "encoder1".."encoder4", hidden states (B, 2^l c, Hp/2^l, Wp/2^l).
    """

    def __init__(self, in_channels: int = 2, base_width: int | None = None, width: str = "paper",
                 flow_scaling: float = 128.0):
        super().__init__(in_channels, base_width, width, flow_scaling)
        _add_recurrent_encoder(self, ConvGRU)

    encode = _recurrent_encode


class UNetXLIFEncoder(_Baseline):
    """EV-MGRFlowNet's U-Net whose encoders are single spiking :class:`agents.spiking.ConvXLIF`
    layers (adaptive threshold with learnable t0, t1, surrogate ``1 / (1 + (10 v)^2)``); the
    residual module and decoder are not spiking. Not Hagenaars' XLIF-EV-FlowNet (see
    :class:`XLIFEVFlowNet`).

    State per encoder l: "encoder{l}_v" membrane potential, "encoder{l}_z" last spikes (both
    (B, 2^l c, Hp/2^l, Wp/2^l)), "encoder{l}_trace" presynaptic trace (B, 1, Hp/2^l, Wp/2^l).
    """

    def __init__(self, in_channels: int = 2, base_width: int | None = None, width: str = "paper",
                 flow_scaling: float = 128.0):
        super().__init__(in_channels, base_width, width, flow_scaling)
        self.neurons = nn.ModuleList(ConvXLIF(i, o) for i, o in zip(*_channels(self.in_channels, self.base_width)))

    def encode(self, x: Tensor, state: State, new_state: State) -> list[Tensor]:
        skips = []
        for level, layer in enumerate(self.neurons):
            key = f"encoder{level + 1}"
            previous = None
            if f"{key}_v" in state:
                previous = (state[f"{key}_v"], state[f"{key}_z"], state[f"{key}_trace"])
            x, (v, z, trace) = layer(x, previous)
            new_state[f"{key}_v"], new_state[f"{key}_z"], new_state[f"{key}_trace"] = v, z, trace
            skips.append(x)
        return skips
