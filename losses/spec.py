"""The loss's specification (:class:`LossSpec`): which loss a window is scored with, the weights
of its terms and the border rule's settings, in one frozen value that the env's reward, training,
the contrast-maximisation solver and the teacher are all given whole (docs/method.md, "Losses").

Not in it: ``flow_scaling`` (pixels per network unit in the smoothness term), a property of the
flow being scored: a network's output scaling, the env's action scale, a solver level's sensor
grid (``losses.contrast_maximisation_flow`` divides it by each level's coarsening); and the
readings the paper leaves open (``upsampling``, ``reference_times``, ``at_normalisation``), which
only training sets and which stay keywords of ``window_loss``.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from dataclasses import KW_ONLY, dataclass
from typing import Literal

import torch

__all__ = ["LossSpec", "LossWeights", "LOSS_NAMES", "BORDER_RAMP", "check_border_ramp", "border_weight"]

#: The losses a window can be scored with: L_HMC (eq. 17) or the baseline L_AT (eq. 14 + smoothing).
LOSS_NAMES = ("hmc", "at")
LossName = Literal["hmc", "at"]

#: The border rule's ramp (pixels) that the env's reward, the learner and the loss functions use
#: by default (docs/results.md, fifth round).
BORDER_RAMP = 16.0


def check_border_ramp(border_ramp) -> float:
    """The ramp as a float; ValueError unless it is a finite number of pixels >= 0."""
    ramp = float(border_ramp)
    if not ramp >= 0 or ramp == float("inf"):
        raise ValueError(f"border_ramp must be a finite number of pixels >= 0, got {border_ramp!r}")
    return ramp


def _check_choice(name: str, value, allowed: tuple) -> None:
    if value not in allowed:
        raise ValueError(f"{name} must be one of {allowed}, got {value!r}")


def _non_negative(name: str, value) -> float:
    number = float(value)
    if not (math.isfinite(number) and number >= 0):
        raise ValueError(f"{name} must be a finite number >= 0, got {value!r}")
    return number


@dataclass(frozen=True)
class LossSpec:
    """The loss of a window: L_HMC (eq. 17) or L_AT, its weights, and the border rule
    (docs/method.md, "Losses"). The defaults are the env's reward: L_HMC with the paper's
    lambda_1, lambda_2 and alpha, and the project's border rule on. Every other default of these
    settings is read from here.

    The weights come first, in their historical order (``LossSpec(1.0, 1e-3, 0.6, 1.0, 16.0)``
    as ``LossWeights`` took them); ``loss`` is keyword-only."""

    lambda_1: float = 1.0
    """weight of the event-count term L_EC (L_HMC only)"""
    lambda_2: float = 1e-3
    """weight of the smoothness term"""
    alpha: float = 0.6
    """exponent of the event-count term L_EC (eqs. 15-16; L_HMC only)"""
    border_penalty: float = 1.0
    """border rule: x the window's zero-flow loss x the share of its events pushed out of the image"""
    border_ramp: float = BORDER_RAMP
    """the border rule's ramp, pixels beyond the border (0: the plain share)"""
    _: KW_ONLY
    loss: LossName = "hmc"
    """"hmc" (L_HMC, eq. 17) or "at" (the baseline L_AT: no event-count term)"""

    def __post_init__(self) -> None:
        _check_choice("loss", self.loss, LOSS_NAMES)
        for name in ("lambda_1", "lambda_2", "alpha", "border_penalty"):
            object.__setattr__(self, name, _non_negative(name, getattr(self, name)))
        object.__setattr__(self, "border_ramp", check_border_ramp(self.border_ramp))

    def of(self, loss: LossName | None = None) -> dict:
        """The keyword arguments of ``hmc_loss`` / ``at_loss`` for ``loss`` (default: the spec's;
        the border penalty is per window: :func:`border_weight`)."""
        loss = self.loss if loss is None else loss
        _check_choice("loss", loss, LOSS_NAMES)
        weights = {"lambda_2": self.lambda_2, "border_ramp": self.border_ramp}
        return {**weights, "lambda_1": self.lambda_1, "alpha": self.alpha} if loss == "hmc" else weights

    def to_dict(self) -> dict:
        """The spec as a JSON-able dict (:meth:`from_dict` inverts it)."""
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, data: Mapping) -> LossSpec:
        """The spec of a dict as :meth:`to_dict` writes it; missing keys keep their defaults, an
        unknown key is a ValueError."""
        unknown = sorted(set(data) - set(_FIELDS))
        if unknown:
            raise ValueError(f"LossSpec: unknown settings {unknown}; known: {list(_FIELDS)}")
        return cls(**data)

    @classmethod
    def from_options(cls, options=None, /, **overrides) -> LossSpec:
        """The spec from the fields of ``options`` that bear a setting's name (a TrainConfig, a
        CMaxSettings, a TeacherSettings, a parsed command line, or a mapping), with ``overrides``
        on top; a setting that neither gives, or gives as None, keeps its default."""
        if options is None:
            given = {}
        elif isinstance(options, Mapping):
            given = {name: options[name] for name in _FIELDS if name in options}
        else:
            given = {name: getattr(options, name) for name in _FIELDS if hasattr(options, name)}
        given.update(overrides)
        return cls(**{name: value for name, value in given.items() if value is not None})


_FIELDS = tuple(f.name for f in dataclasses.fields(LossSpec))

#: The spec's earlier name (it held the weights alone); the same class.
LossWeights = LossSpec


def border_weight(border_penalty: float, zero_flow: torch.Tensor) -> float | torch.Tensor:
    """The border rule's weight of each window: ``border_penalty`` x the window's loss under zero
    flow ((B,), no graph); 0.0 when the penalty is 0. The loss charges this weight x the (ramped)
    share of the window's events pushed out of the image."""
    return border_penalty * zero_flow if border_penalty else 0.0
