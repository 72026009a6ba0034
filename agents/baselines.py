"""Baselines with EV-MGRFlowNet's interface (REFERENCE section 4): EV-FlowNet,
ConvGRU-EV-FlowNet (Hagenaars' RecEVFlowNet) and XLIF-EV-FlowNet (spiking encoder).

All share the U-Net of :class:`agents.flownet.FlowNetBase`: four stride-2 encoders, two residual
blocks, four decoders with skips and the previous scale's flow concatenated, tanh heads at
1/8..1. They differ only in the encoder and the state it carries.
"""

from __future__ import annotations

from torch import Tensor, nn

from .flownet import FlowNetBase, State, resolve_base_width
from .layers import ConvDown, ConvGRU
from .spiking import ConvXLIF


def _channels(in_channels: int, c: int) -> tuple[list[int], list[int]]:
    outputs = [2 * c, 4 * c, 8 * c, 16 * c]
    return [in_channels] + outputs[:-1], outputs


class EVFlowNet(FlowNetBase):
    """EV-FlowNet: the same U-Net with no recurrence (encoders are conv_down only).

    Stateless: the returned state is an empty dict.
    Args: as :class:`agents.evmgrflownet.EVMGRFlowNet` (no ablation switches).
    """

    def __init__(
        self,
        in_channels: int = 2,
        base_width: int | None = None,
        width: str = "paper",
        flow_scaling: float = 128.0,
    ):
        c = resolve_base_width(base_width, width)
        super().__init__(in_channels, c, flow_scaling, use_prior_flow=False)
        self.downs = nn.ModuleList(ConvDown(i, o) for i, o in zip(*_channels(in_channels, c)))
        self.config = {
            "in_channels": self.in_channels,
            "base_width": self.base_width,
            "flow_scaling": self.flow_scaling,
        }

    def encode(self, x: Tensor, state: State, new_state: State) -> list[Tensor]:
        skips = []
        for down in self.downs:
            x = down(x)
            skips.append(x)
        return skips


class ConvGRUEVFlowNet(FlowNetBase):
    """ConvGRU-EV-FlowNet: every encoder is conv_down + ConvGRU (eq. 4).

    State: "encoder1".."encoder4", hidden states (B, 2^l c, Hp/2^l, Wp/2^l).
    """

    def __init__(
        self,
        in_channels: int = 2,
        base_width: int | None = None,
        width: str = "paper",
        flow_scaling: float = 128.0,
    ):
        c = resolve_base_width(base_width, width)
        super().__init__(in_channels, c, flow_scaling, use_prior_flow=False)
        inputs, outputs = _channels(in_channels, c)
        self.downs = nn.ModuleList(ConvDown(i, o) for i, o in zip(inputs, outputs))
        self.grus = nn.ModuleList(ConvGRU(o, o) for o in outputs)
        self.config = {
            "in_channels": self.in_channels,
            "base_width": self.base_width,
            "flow_scaling": self.flow_scaling,
        }

    def encode(self, x: Tensor, state: State, new_state: State) -> list[Tensor]:
        skips = []
        for level, (down, gru) in enumerate(zip(self.downs, self.grus)):
            key = f"encoder{level + 1}"
            x = new_state[key] = gru(down(x), state.get(key))
            skips.append(x)
        return skips


class XLIFEVFlowNet(FlowNetBase):
    """XLIF-EV-FlowNet: the encoders are spiking ConvXLIF layers (adaptive-threshold LIF, soft
    reset, arctan surrogate gradient; t0 = 0.01, t1 = 1.8 at init); the skips are spike maps.

    Choice: only the encoder neurons spike (REFERENCE section 4 fixes the encoder); the residual
    module and decoder are EV-FlowNet's, so every model shares one decoder and one output format.

    State per encoder l: "encoder{l}_v" membrane potential, "encoder{l}_z" last spikes (both
    (B, 2^l c, Hp/2^l, Wp/2^l)), "encoder{l}_trace" presynaptic trace (B, 1, Hp/2^l, Wp/2^l).
    """

    def __init__(
        self,
        in_channels: int = 2,
        base_width: int | None = None,
        width: str = "paper",
        flow_scaling: float = 128.0,
    ):
        c = resolve_base_width(base_width, width)
        super().__init__(in_channels, c, flow_scaling, use_prior_flow=False)
        self.neurons = nn.ModuleList(ConvXLIF(i, o) for i, o in zip(*_channels(in_channels, c)))
        self.config = {
            "in_channels": self.in_channels,
            "base_width": self.base_width,
            "flow_scaling": self.flow_scaling,
        }

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
