"""The terms of the loss, registered by name (docs/method.md, "Losses").

A loss is a weighted sum of the terms of :data:`TERMS`, in the registry's order:
``L = sum_n w_n T_n``, over the terms that the loss (``"hmc"`` or ``"at"``) includes and whose
weight is not 0. A term is a function of one scale's :class:`TermInputs` that gives its value
per window, (B,); its weight is named by the field of :class:`losses.LossSpec` that holds it
(None: weight 1). The caller hands the weights in as a mapping from those names to numbers, or
to (B,) tensors of per-window weights (the border rule's); a name it does not give weighs 0.

Adding a term touches its function and one line of :data:`TERMS` (and, where its weight is a
new setting rather than an existing one, that setting's field of ``LossSpec``).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from functools import cached_property

import torch

from .events import EventBatch
from .image_terms import AtNormalisation, event_image_terms
from .smoothness import charbonnier_smoothness
from .spec import LOSS_NAMES
from .warp import beyond_image, warp_events

__all__ = ["Term", "TermInputs", "TERMS", "term_values", "combine_terms", "ramped_dropped_share"]

Weight = float | torch.Tensor


@dataclass(eq=False)
class TermInputs:
    """What the terms read on one scale: the events (``tau`` in windows: k + tau for window k of
    K accumulated ones), the flow at each event ``u`` (B, N, 2), the full-resolution flows the
    smoothness term reads with their event-pixel masks (one per window), the image size, the
    reference times and the span they cover, and the loss's settings. The event images (L_AT,
    L_EC and the kept splat weight, one fused pass) are computed once, when a term first asks."""

    events: EventBatch
    u: torch.Tensor
    flows: Sequence[torch.Tensor]
    masks: Sequence[torch.Tensor]
    height: int
    width: int
    references: tuple[float, ...]
    span: float
    alpha: float
    flow_scaling: float
    border_ramp: float
    at_normalisation: AtNormalisation

    @cached_property
    def images(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(B, R) L_AT(s), L_EC(s) and the splat weight kept inside the image, per reference time."""
        return event_image_terms(self.events, self.u, self.height, self.width, self.references, self.span,
                                 self.alpha, self.at_normalisation)

    @cached_property
    def dropped(self) -> torch.Tensor:
        """(B, R) the share of the valid events' splat weight outside the image (0: no events)."""
        n_valid = self.events.mask.sum(dim=1).to(self.u.dtype)  # (B,)
        kept = self.images[2] / n_valid.clamp_min(1).unsqueeze(1)
        return torch.where(n_valid.unsqueeze(1) > 0, 1 - kept, torch.zeros_like(kept))


def ramped_dropped_share(events: EventBatch, u, height, width, references, ramp) -> torch.Tensor:
    """(B, R) the border charge per reference time with a distance ramp of ``ramp`` pixels.

    Each valid event's charge is the share of its bilinear splat weight that falls outside the
    image times ``min(1, d / ramp)``, d = the L1 distance (pixels) by which the warped event
    lies beyond the image; the mean over valid events. Events just across the border (real
    motion leaves by at most |u| pixels) cost little; events pushed far out cost their whole
    dropped share, as with no ramp (``ramp -> 0`` gives the plain dropped share).
    """
    x, y, t, _, mask = events
    m = mask.to(u.dtype)
    n = m.sum(dim=1).clamp_min(1)
    out = []
    for s in references:
        xw, yw = warp_events(x.to(u.dtype), y.to(u.dtype), t.to(u.dtype), u, s)
        kx = torch.minimum(xw + 1, width - xw).clamp(0, 1)  # share of the x-weights on the sensor
        ky = torch.minimum(yw + 1, height - yw).clamp(0, 1)
        charge = (1 - kx * ky) * (beyond_image(xw, yw, height, width) / ramp).clamp(max=1)
        out.append((charge * m).sum(dim=1) / n)
    return torch.stack(out, dim=1)


def average_timestamp_term(x: TermInputs) -> torch.Tensor:
    """L_AT(s0) + L_AT(s1) (eq. 14)."""
    return x.images[0].sum(dim=1)


def event_count_term(x: TermInputs) -> torch.Tensor:
    """L_EC(s0) + L_EC(s1) (eqs. 15-16)."""
    return x.images[1].sum(dim=1)


def smoothness_term(x: TermInputs) -> torch.Tensor:
    """The Charbonnier smoothness of the flows on their event pixels, the mean over the flows."""
    return sum(charbonnier_smoothness(f, m, x.flow_scaling) for f, m in zip(x.flows, x.masks)) / len(x.flows)


def border_term(x: TermInputs) -> torch.Tensor:
    """The border charge summed over the reference times: the dropped share, ramped over
    ``border_ramp`` pixels when it is > 0 (:func:`ramped_dropped_share`)."""
    if x.border_ramp > 0:
        charge = ramped_dropped_share(x.events, x.u, x.height, x.width, x.references, x.border_ramp)
    else:
        charge = x.dropped
    return charge.sum(dim=1)


@dataclass(frozen=True)
class Term:
    """One term of the loss: ``value`` its (B,) value on one scale; ``weight`` the name of the
    weight that multiplies it (a ``LossSpec`` field; None: 1); ``losses`` the losses that include
    it; ``logged`` whether ``LossOutput.components`` reports it (the mean over scales, detached;
    computed then even where the loss leaves it out)."""

    value: Callable[[TermInputs], torch.Tensor]
    weight: str | None = None
    losses: tuple[str, ...] = LOSS_NAMES
    logged: bool = True


#: The registry: name -> term, in the order of the sum (eq. 17, and the border rule last).
TERMS: dict[str, Term] = {
    "at": Term(average_timestamp_term),
    "smooth": Term(smoothness_term, "lambda_2"),
    "ec": Term(event_count_term, "lambda_1", losses=("hmc",)),
    "border": Term(border_term, "border_penalty", logged=False),
}


def _weight_of(term: Term, weights: Mapping[str, Weight]) -> Weight | None:
    """The term's weight (None: 1; a name not in ``weights``: 0)."""
    return None if term.weight is None else weights.get(term.weight, 0.0)


def _in_loss(term: Term, loss: str, weights: Mapping[str, Weight]) -> bool:
    weight = _weight_of(term, weights)
    return loss in term.losses and (weight is None or isinstance(weight, torch.Tensor) or weight != 0)


def term_values(inputs: TermInputs, loss: str, weights: Mapping[str, Weight]) -> dict:
    """{name: (B,)} every term that the loss weighs or that is logged, on one scale, and
    ``"dropped"`` (B, R), the share of splat weight outside the image."""
    values = {name: term.value(inputs) for name, term in TERMS.items() if term.logged or _in_loss(term, loss, weights)}
    values["dropped"] = inputs.dropped
    return values


def combine_terms(per_scale: Sequence[dict], loss: str, weights: Mapping[str, Weight]):
    """(per_sample (B,), components) of the loss from the :func:`term_values` of each scale:
    per scale the weighted sum of its terms, then the mean over scales. Components: every logged
    term and ``"kept"`` (1 - the dropped share, mean over reference times), means over scales,
    detached."""
    per = []
    for values in per_scale:
        total = None
        for name, term in TERMS.items():
            if not _in_loss(term, loss, weights):
                continue
            weight = _weight_of(term, weights)
            part = values[name] if weight is None else weight * values[name]
            total = part if total is None else total + part
        per.append(total)
    n = len(per_scale)
    per_sample = sum(per) / n
    components = {
        name: (sum(values[name] for values in per_scale) / n).detach() for name, term in TERMS.items() if term.logged
    }
    components["kept"] = (1 - sum(values["dropped"] for values in per_scale) / n).mean(dim=1).detach()
    return per_sample, components
