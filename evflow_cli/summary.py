"""The model variants reported in tables (the paper's models and ablations) and their sizes."""

from __future__ import annotations

import torch
from torch import nn
from torch.utils.flop_counter import FlopCounterMode

from agents.registry import make_model

#: (label, registry name, extra kwargs): every built-in model and EV-MGRFlowNet's two ablations.
MODEL_VARIANTS: list[tuple[str, str, dict]] = [
    ("EV-MGRFlowNet", "ev-mgrflownet", {}),
    ("EV-MGRFlowNet w/o ST-ConvGRU", "ev-mgrflownet", {"use_st_convgru": False}),
    ("EV-MGRFlowNet w/o prior flows", "ev-mgrflownet", {"use_prior_flow": False}),
    ("ConvGRU-EV-FlowNet", "convgru-ev-flownet", {}),
    ("EV-FlowNet", "ev-flownet", {}),
    ("XLIF-EV-FlowNet", "xlif-ev-flownet", {}),
]


def count_parameters(model: nn.Module, trainable_only: bool = True) -> int:
    return sum(p.numel() for p in model.parameters() if p.requires_grad or not trainable_only)


def parameter_table(width: str = "paper") -> list[tuple[str, int]]:
    """(label, trainable parameter count) of every variant at the named width preset."""
    return [
        (label, count_parameters(make_model(name, width=width, **kwargs)))
        for label, name, kwargs in MODEL_VARIANTS
    ]


def forward_flops(model: nn.Module, batch: int = 1, height: int = 256, width: int = 256) -> int:
    """Floating-point operations of the convolutions and matrix products (2 per multiply-add)
    in one forward window of ``model`` with a carried state (the second window of a sequence,
    so that every recurrent path runs); elementwise arithmetic is not counted. Built-in networks
    are counted on their torch reference path (NCHW, ``channels_last = False``): the CPU path
    computes some convolutions inside compiled kernels, which the counter does not see."""
    x = torch.zeros(batch, getattr(model, "in_channels", 2), height, width)
    x[:, :, ::3, ::5] = 1.0
    had_layout = "channels_last" in vars(model)
    layout = getattr(model, "channels_last", None)
    if hasattr(model, "channels_last"):
        model.channels_last = False
    try:
        with torch.no_grad():
            _, state = model(x, None)
            counter = FlopCounterMode(display=False)
            with counter:
                model(x, state)
    finally:
        if had_layout:
            model.channels_last = layout
        elif hasattr(model, "channels_last"):
            del model.channels_last
    return int(counter.get_total_flops())


def flops_table(width: str = "paper", batch: int = 1, height: int = 256, size_w: int = 256) -> list[tuple[str, int]]:
    """(label, :func:`forward_flops`) of every variant at the named width preset."""
    return [
        (label, forward_flops(make_model(name, width=width, **kwargs), batch, height, size_w))
        for label, name, kwargs in MODEL_VARIANTS
    ]


def forward_latency_ms(model: nn.Module, height: int = 128, width: int = 128, *, device: str = "cpu",
                       repeats: int = 20, warmup: int = 5) -> float:
    """Median wall time (milliseconds) of one forward window of ``model`` with a carried state
    (batch 1, ``height`` x ``width``, no gradients, the model's own layout), after ``warmup``
    untimed windows (the first calls compile kernels); a machine shared with other jobs makes it
    longer."""
    import time

    x = torch.zeros(1, getattr(model, "in_channels", 2), height, width, device=device)
    x[:, :, ::3, ::5] = 1.0
    model = model.to(device)
    times = []
    with torch.no_grad():
        state = None
        for _ in range(warmup):
            _, state = model(x, state)
        for _ in range(repeats):
            if device.startswith("cuda"):
                torch.cuda.synchronize()
            began = time.perf_counter()
            _, state = model(x, state)
            if device.startswith("cuda"):
                torch.cuda.synchronize()
            times.append(time.perf_counter() - began)
    times.sort()
    return 1e3 * times[len(times) // 2]
