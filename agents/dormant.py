"""Dormant ReLU channels: finding the channels of a network that fire on no window, and giving a
flow decoder's dormant channels a second start.

A ReLU channel whose output is zero on every pixel of every window passes no gradient to its
incoming weights, so training alone never brings it back. :func:`revive_decoder` re-initialises
the incoming weights of such channels in a :class:`agents.flownet.FlowDecoder` and zeroes their
outgoing weights (the recipe of ReDo, Sokar et al. 2023, "The Dormant Neuron Phenomenon in Deep
Reinforcement Learning"): the network's flow is exactly what it was, and the outgoing weights,
which now see a live input, receive a gradient from the first update on.

In a flow decoder the consumers of stage ``l``'s output channel ``c`` are known: the flow head
of scale ``l`` (its input channel ``c``) and the next stage's convolution (its input channel
``c``: the stage's output comes first in the concatenation of eq. 10).
"""

from __future__ import annotations

import torch
from torch import nn

from agents.evmgrflownet import DeepMemoryUp
from agents.flownet import FlowDecoder
from agents.layers import ConvDown, ConvUp, ConvUpNearestReflect, ResidualBlock

__all__ = ["RELU_LAYERS", "FiringRecord", "relu_layers", "revive_decoder"]

#: layers whose output is a ReLU's (zero = not firing)
RELU_LAYERS = (ConvDown, ConvUp, ConvUpNearestReflect, ResidualBlock, DeepMemoryUp)


def relu_layers(model: nn.Module) -> list[tuple[str, nn.Module]]:
    """(name, layer) of every layer of ``model`` whose output is a ReLU's, in the model's order."""
    return [(name, module) for name, module in model.named_modules() if isinstance(module, RELU_LAYERS)]


class FiringRecord:
    """Forward hooks on a model's ReLU layers: per layer, which channels were ever positive and
    how many outputs were zero, over every forward pass while attached."""

    def __init__(self, model: nn.Module) -> None:
        self.fired: dict[str, torch.Tensor] = {}
        self.zeros: dict[str, int] = {}
        self.outputs: dict[str, int] = {}
        self.handles = [layer.register_forward_hook(self._hook(name)) for name, layer in relu_layers(model)]

    def _hook(self, name: str):
        def record(_module, _inputs, out: torch.Tensor) -> None:
            fired = (out > 0).transpose(0, 1).reshape(out.shape[1], -1).any(dim=1).cpu()
            self.fired[name] = fired if name not in self.fired else self.fired[name] | fired
            self.zeros[name] = self.zeros.get(name, 0) + int((out == 0).sum())
            self.outputs[name] = self.outputs.get(name, 0) + out.numel()
        return record

    def close(self) -> None:
        for handle in self.handles:
            handle.remove()

    def summary(self) -> dict[str, dict]:
        """Per layer: ``dead`` (channels never positive), ``channels``, ``dead_channels`` (their
        indices) and ``zero_share`` (of all outputs)."""
        return {name: {"dead": int((~fired).sum()), "channels": int(fired.numel()),
                       "dead_channels": [int(i) for i in torch.nonzero(~fired).flatten()],
                       "zero_share": self.zeros[name] / max(self.outputs[name], 1)}
                for name, fired in self.fired.items()}


@torch.no_grad()
def revive_decoder(model: nn.Module, fired: dict[str, torch.Tensor], seed: int = 0) -> dict[str, int]:
    """Re-initialise the decoder stages' channels that never fired; the flow is unchanged.

    model: a network with a :class:`FlowDecoder` as ``model.decoder`` (EV-MGRFlowNet,
    EV-FlowNet, ConvGRU-EV-FlowNet). fired: :attr:`FiringRecord.fired` of that network, (C,) bool
    per layer name (``decoder.upsamples.l``); stages missing from it are left alone. seed: of the
    fresh weights, drawn as the stage's own class draws them (a new layer of the same shape).
    Returns the number of channels revived per stage name."""
    decoder = getattr(model, "decoder", None)
    if type(decoder) is not FlowDecoder:  # a subclass may concatenate its stages' inputs otherwise
        raise ValueError(f"{type(model).__name__}: reviving dormant channels needs a FlowDecoder as .decoder, "
                         f"found {type(decoder).__name__}")
    dormant = {level: torch.nonzero(~fired[f"decoder.upsamples.{level}"].to(torch.bool)).flatten().tolist()
               for level in range(len(decoder.upsamples)) if f"decoder.upsamples.{level}" in fired}
    dormant = {level: channels for level, channels in dormant.items() if channels}
    with torch.random.fork_rng(devices=[]):
        torch.default_generator.manual_seed(seed)  # the CPU generator only: fork_rng restores it, and no other
        for level, channels in dormant.items():  # incoming first, so that no fresh row reads a revived channel
            conv = decoder.upsamples[level].conv
            fresh = type(decoder.upsamples[level])(conv.in_channels, conv.out_channels).conv
            conv.weight[channels] = fresh.weight[channels].to(conv.weight)
            if conv.bias is not None:
                conv.bias[channels] = fresh.bias[channels].to(conv.bias)
    for level, channels in dormant.items():  # then outgoing: the flow head of this scale and the next stage
        decoder.heads[level].weight[:, channels] = 0
        if level + 1 < len(decoder.upsamples):  # (this stage's output comes first in its input)
            decoder.upsamples[level + 1].conv.weight[:, channels] = 0
    return {f"decoder.upsamples.{level}": len(channels) for level, channels in dormant.items()}
