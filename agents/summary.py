"""The model variants reported in tables (the paper's models and ablations) and their sizes."""

from __future__ import annotations

from torch import nn

from .registry import make_model

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
