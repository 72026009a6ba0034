"""Models by name, and how a user brings their own.

Built-in names (``MODELS``): "ev-mgrflownet"; the published baselines as their authors built
them, "ev-flownet" (Zhu et al.; 4-channel input by default: train it with
``--input count_time_image``), "convgru-ev-flownet" and "xlif-ev-flownet" (Hagenaars et al.);
and the project's earlier stand-ins, EV-MGRFlowNet's U-Net without recurrence
("unet-feedforward"), with eq. 4 ConvGRU encoders ("unet-convgru") or with spiking encoders
only ("unet-xlif-encoder"). Each accepts ``in_channels``, ``base_width`` (paper 32), ``width``
("paper" | "cpu", used when ``base_width`` is None) and ``flow_scaling=128.0``; EV-MGRFlowNet also
``use_st_convgru`` and ``use_prior_flow`` (the paper's ablations). Each built-in model keeps its
constructor kwargs in ``model.config``, so ``make_model(name, **model.config)`` rebuilds it.

Bringing your own model
-----------------------
Write a factory (a class or a function) that returns a ``torch.nn.Module`` honouring the
protocol of ``agents/protocol.py`` (``forward(x, state) -> (flows, state)``; an all-zeros state
entry must mean a fresh sequence). Then either

- pass ``package.module:factory`` wherever a model name is accepted (e.g. ``--model
  my_pkg.my_flow:build``, with ``my_pkg`` importable, e.g. on ``PYTHONPATH``), or
- call ``register_model("my-flow", build)`` before the scripts look the name up.

The factory receives the keyword arguments the caller passes. The common ones (``in_channels``,
``base_width``, ``width``, ``flow_scaling``) are dropped if the factory's signature does not
name them and has no ``**kwargs``; any other keyword is passed through. A dotted-path model is
checked once with :func:`agents.protocol.check_protocol` (three tiny forward passes); if it has no
``config`` attribute, one is set to the kwargs it was built with.
"""

from __future__ import annotations

import importlib
import inspect
from typing import Callable

from torch import nn

from .baselines import ConvGRUEVFlowNet, EVFlowNet, UNetConvGRU, UNetFeedforward, UNetXLIFEncoder, XLIFEVFlowNet
from .evmgrflownet import EVMGRFlowNet
from .protocol import ModelLoadError, ProtocolError, check_protocol

ModelFactory = Callable[..., nn.Module]

MODELS: dict[str, ModelFactory] = {
    "ev-mgrflownet": EVMGRFlowNet,
    "ev-flownet": EVFlowNet,
    "convgru-ev-flownet": ConvGRUEVFlowNet,
    "xlif-ev-flownet": XLIFEVFlowNet,
    "unet-feedforward": UNetFeedforward,
    "unet-convgru": UNetConvGRU,
    "unet-xlif-encoder": UNetXLIFEncoder,
}

#: Keyword arguments every script may pass; silently dropped for factories that do not take them.
COMMON_KWARGS = frozenset({"in_channels", "base_width", "width", "flow_scaling"})


def width_kwargs(width: str | int) -> dict:
    """make_model's width keyword: ``width`` for 'paper' / 'cpu', ``base_width`` for an integer
    (or its digits)."""
    return {"base_width": int(width)} if str(width).isdigit() else {"width": width}


def register_model(name: str, factory: ModelFactory, overwrite: bool = False) -> None:
    """Make ``factory`` available as ``make_model(name, ...)``."""
    if ":" in name:
        raise ValueError(f"model names may not contain ':' (reserved for dotted paths): {name!r}")
    if not callable(factory):
        raise TypeError(f"factory for {name!r} must be callable, got {type(factory).__name__}")
    if name in MODELS and not overwrite and MODELS[name] is not factory:
        raise ValueError(f"model {name!r} is already registered (pass overwrite=True to replace it)")
    MODELS[name] = factory


def load_factory(dotted_path: str) -> ModelFactory:
    """Import ``package.module:factory`` (the attribute may itself be dotted: ``mod:Class.build``)."""
    module_name, _, attribute = dotted_path.partition(":")
    if not module_name or not attribute:
        raise ModelLoadError(f"expected 'package.module:factory', got {dotted_path!r}")
    try:
        module = importlib.import_module(module_name)
    except ModuleNotFoundError as error:
        raise ModelLoadError(
            f"cannot import module {module_name!r} for model {dotted_path!r} ({error}); "
            "is its package installed or on PYTHONPATH?"
        ) from error
    target = module
    for part in attribute.split("."):
        if not hasattr(target, part):
            raise ModelLoadError(f"module {module_name!r} has no attribute {attribute!r}")
        target = getattr(target, part)
    if not callable(target):
        raise ModelLoadError(f"{dotted_path!r} is not callable (expected a class or a function)")
    return target


def _accepted_kwargs(factory: ModelFactory, kwargs: dict) -> dict:
    try:
        parameters = inspect.signature(factory).parameters
    except (TypeError, ValueError):  # builtins without a signature: pass everything
        return kwargs
    if any(p.kind is inspect.Parameter.VAR_KEYWORD for p in parameters.values()):
        return kwargs
    return {k: v for k, v in kwargs.items() if k in parameters or k not in COMMON_KWARGS}


def make_model(name_or_dotted_path: str, **kwargs) -> nn.Module:
    """Build a flow model by registered name or by ``package.module:factory``.

    Raises:
        ModelLoadError: unknown name, missing module or attribute.
        ProtocolError: the built object does not honour the protocol (a ModelLoadError).
    """
    spec = name_or_dotted_path
    if ":" in spec:
        factory = load_factory(spec)
        external = True
    elif spec in MODELS:
        factory = MODELS[spec]
        external = spec not in _BUILT_IN
    else:
        raise ModelLoadError(
            f"unknown model {spec!r}; registered: {sorted(MODELS)}, "
            "or give a dotted path 'package.module:factory'"
        )
    passed = _accepted_kwargs(factory, kwargs)
    model = factory(**passed)
    if not isinstance(model, nn.Module):
        raise ProtocolError(f"{spec!r} returned {type(model).__name__}, not a torch.nn.Module")
    if external:
        check_protocol(model, in_channels=int(passed.get("in_channels", getattr(model, "in_channels", 2))))
        if not isinstance(getattr(model, "config", None), dict):
            model.config = dict(passed)
    return model


_BUILT_IN = frozenset(MODELS)
