"""Hybrid motion-compensation loss L_HMC (docs/method.md, "Losses", eq. 17) and the baseline L_AT.

A composite that is only a weighted sum of the terms registered in :mod:`losses.terms`:
``L_HMC = L_AT(0) + L_AT(1) + lambda_1 (L_EC(0) + L_EC(1)) + lambda_2 L_smooth``;
the baseline ``L_AT`` drops the L_EC term (same smoothing). Multi-scale input: every scale is
brought to full resolution, the loss is computed on each and averaged over scales. Over a batch:
the mean over batch elements; a padded batch gives exactly the per-window results.

Known hole (docs/method.md, "Losses"): out-of-image corners are dropped, so a flow that pushes every
event off the sensor scores L_AT = L_EC = 0. ``components["kept"]`` reports the share of the
events' splat weight that stayed inside the image (mean over the reference times), and
``border_penalty`` (default 0, i.e. the paper's loss) adds
``border_penalty * sum_s (1 - kept_s)`` for the project to close the hole with; it is a float
or a (B,) tensor of per-window weights (the env and the learner pass a multiple of each
window's zero-flow loss, so that pushing events out never pays, however dense the window:
``losses.window_loss`` with a :class:`losses.LossSpec`). ``border_ramp`` defaults to the spec's.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal, Mapping, Sequence, get_args

import torch
import torch.nn.functional as F

from ._validation import check_events, check_flow
from .events import EventBatch
from .image_terms import AT_NORMALISATIONS, AtNormalisation
from .sampling import sample_flow
from .smoothness import event_pixel_mask
from .spec import BORDER_RAMP, LossSpec, LossWeights, _check_choice, border_weight, check_border_ramp
from .terms import TermInputs, Weight, combine_terms, ramped_dropped_share, term_values
from .warp import outside_distance

__all__ = ["LossOutput", "hmc_loss", "at_loss", "accumulated_hmc_loss", "to_full_resolution",
           "ramped_dropped_share", "check_border_ramp", "BORDER_RAMP", "Upsampling", "ReferenceTimes",
           "UPSAMPLINGS", "REFERENCE_TIMES", "AtNormalisation", "AT_NORMALISATIONS", "LossWeights",
           "border_rule_weight"]

#: How a coarse scale's flow is brought to full resolution for the loss (the paper does not say).
Upsampling = Literal["bilinear", "nearest"]
UPSAMPLINGS = get_args(Upsampling)
#: Where the two reference times sit: the window's bounds (tau = 0 and 1; with K accumulated
#: windows 0 and K), or the first and last valid event of the window(s).
ReferenceTimes = Literal["window", "events"]
REFERENCE_TIMES = get_args(ReferenceTimes)

FlowInput = torch.Tensor | Sequence[torch.Tensor]


def border_rule_weight(loss_fn, zero_flow: torch.Tensor, events: EventBatch, border_penalty: float, **loss_kwargs):
    """The border rule's weight of each window (:func:`losses.spec.border_weight`) with the
    zero-flow loss ``loss_fn(zero_flow, events, **loss_kwargs)`` (no graph), (B,); 0.0 when the
    penalty is 0 (the loss is then not computed)."""
    if not border_penalty:
        return 0.0
    with torch.no_grad():
        return border_weight(border_penalty, loss_fn(zero_flow, events, **loss_kwargs).per_sample)


@dataclass(frozen=True)
class LossOutput:
    """loss: () scalar, mean of ``per_sample``. per_sample: (B,) loss per window (graph kept).
    components: (B,) detached tensors, averaged over scales: "at" = L_AT(0) + L_AT(1),
    "ec" = L_EC(0) + L_EC(1), "smooth" = L_smooth, "kept" = share of valid events' splat weight
    inside the image (mean over reference times; 1 for an empty window)."""

    loss: torch.Tensor
    per_sample: torch.Tensor
    components: dict


def to_full_resolution(flow: FlowInput, upsampling: Upsampling = "bilinear") -> list[torch.Tensor]:
    """Validate and bring every scale to full resolution.

    flow: (B, 2, H, W) tensor, or a list of such tensors at several resolutions, all in pixels
    per window at FULL sensor resolution (docs/method.md, "Conventions"). Full resolution = the largest H and
    largest W in the list. Coarser scales are upsampled without rescaling the values, since they
    are already in full-resolution pixels: ``upsampling`` "bilinear" (default,
    ``F.interpolate(..., align_corners=False)``) or "nearest" (each coarse cell's vector over
    the pixels it covers). Returns a list of (B, 2, H, W) tensors.
    Raises ValueError for an empty list, a bad shape, NaN/inf, differing batch sizes or an
    unknown ``upsampling``.
    """
    _check_choice("upsampling", upsampling, UPSAMPLINGS)
    flows = [flow] if isinstance(flow, torch.Tensor) else list(flow)
    if not flows:
        raise ValueError("flow: empty list of scales")
    for j, f in enumerate(flows):
        check_flow(f, name="flow" if len(flows) == 1 else f"flow[{j}]")
    B = flows[0].shape[0]
    if any(f.shape[0] != B for f in flows):
        raise ValueError(f"flow scales have different batch sizes {[f.shape[0] for f in flows]}")
    H = max(f.shape[2] for f in flows)
    W = max(f.shape[3] for f in flows)
    if upsampling == "nearest":
        return [f if f.shape[2:] == (H, W) else F.interpolate(f, size=(H, W), mode="nearest") for f in flows]
    return [
        f if f.shape[2:] == (H, W)
        else F.interpolate(f, size=(H, W), mode="bilinear", align_corners=False)
        for f in flows
    ]


def rebase_to_events(t: torch.Tensor, u: torch.Tensor, mask: torch.Tensor, span: float):
    """Move the reference times from the window bounds (0 and ``span``) to the first and last
    valid event of each batch element, keeping the flow's units (pixels per window).

    t: (B, N) event times in windows; u: (B, N, 2) pixels per window; mask: (B, N) bool.
    With a = first and b = last event time, returns ``t' = (t - a) span / (b - a)`` and
    ``u' = u (b - a) / span``: then ``(s' - t') u'`` at s' = 0 and s' = span is ``(a - t) u`` and
    ``(b - t) u`` (eq. 12 to the first and last event), and ``1 - |s' - t'| / span`` is the
    closeness ``1 - |s - t| / (b - a)``. Elements whose events all share one time keep the
    window bounds. Differentiable in u.
    """
    big = torch.finfo(t.dtype).max
    first = torch.where(mask, t, big).amin(dim=1, keepdim=True)
    last = torch.where(mask, t, -big).amax(dim=1, keepdim=True)
    spread = last - first
    ok = spread > 0
    first = torch.where(ok, first, torch.zeros_like(first))
    ratio = torch.where(ok, spread / span, torch.ones_like(spread))  # (B, 1)
    return (t - first) / ratio, u * ratio.unsqueeze(-1).to(u.dtype)


def _output(per_sample: torch.Tensor, components: dict) -> LossOutput:
    return LossOutput(loss=per_sample.mean(), per_sample=per_sample, components=components)


def _per_window(flow, events, loss: str, weights: Mapping[str, Weight], alpha, border_ramp, flow_scaling,
                upsampling="bilinear", reference_times="window", at_normalisation="event_pixels") -> LossOutput:
    """The loss ``loss`` of each window: its terms (losses.terms) weighed by ``weights`` (the
    names of the terms' weights; the border term's is per window), on every scale."""
    _check_choice("reference_times", reference_times, REFERENCE_TIMES)
    _check_choice("at_normalisation", at_normalisation, AT_NORMALISATIONS)
    flows = to_full_resolution(flow, upsampling)
    B, _, H, W = flows[0].shape
    check_events(events, batch_size=B)
    events = events.zero_padding()  # padding may hold anything; the torch path reads every slot
    scaling = float(max(H, W)) if flow_scaling is None else float(flow_scaling)
    ramp = check_border_ramp(border_ramp)
    ev_mask = event_pixel_mask(events.x, events.y, events.mask, H, W)
    per_scale = []
    for f in flows:
        u = sample_flow(f, events.x, events.y, events.mask)
        t = events.tau
        if reference_times == "events":
            t, u = rebase_to_events(t.to(u.dtype), u, events.mask, 1.0)
        inputs = TermInputs(events._replace(tau=t), u, [f], [ev_mask], H, W, (0.0, 1.0), 1.0, alpha, scaling, ramp,
                            at_normalisation)
        per_scale.append(term_values(inputs, loss, weights))
    return _output(*combine_terms(per_scale, loss, weights))


def hmc_loss(
    flow: FlowInput,
    events: EventBatch,
    *,
    flow_scaling: float | None = None,
    lambda_1: float = LossSpec.lambda_1,
    lambda_2: float = LossSpec.lambda_2,
    alpha: float = LossSpec.alpha,
    border_penalty: float | torch.Tensor = 0.0,
    border_ramp: float = LossSpec.border_ramp,
    upsampling: Upsampling = "bilinear",
    reference_times: ReferenceTimes = "window",
    at_normalisation: AtNormalisation = "event_pixels",
) -> LossOutput:
    """Hybrid motion-compensation loss, eq. 17, per window.

    flow: (B, 2, H, W) float, pixels of displacement over the window at full sensor resolution,
        or a list of such tensors at several resolutions (see ``to_full_resolution``).
    events: EventBatch of B windows (x, y pixels; tau in [0, 1]; padded with mask).
    flow_scaling: pixels per network unit for the smoothness term; default max(H, W).
    lambda_1, lambda_2, alpha: defaults from :class:`LossSpec` (the paper's). border_penalty: 0 (paper), or the
    weight (float, or (B,) tensor per window) of ``sum_s (1 - kept_s)`` (see the module doc).
    border_ramp: pixels; > 0 charges each event's dropped share times ``min(1, d / border_ramp)``,
    d = how far beyond the image it lands (``ramped_dropped_share``); 0: the plain share.
    Default: the spec's (16), which matters only where ``border_penalty`` is given.
    upsampling: how coarse scales reach full resolution (``to_full_resolution``).
    reference_times: "window" (s = 0 and 1, the window's bounds) or "events" (the first and
    last valid event of each window, ``rebase_to_events``).
    at_normalisation: "event_pixels" (L_AT over N_nz, docs/method.md, "Losses") or "sum" (eq. 14 as
    printed); see ``event_image_terms``.
    Returns LossOutput (loss = mean over batch of per_sample). Events and flow may be on CPU or
    CUDA; computations run in flow's dtype.
    Raises ValueError for a bad flow shape, NaN/inf flow, batch-size mismatch, empty batch,
    tau outside [0, 1] or an unknown choice.
    """
    weights = {"lambda_1": lambda_1, "lambda_2": lambda_2, "border_penalty": border_penalty}
    return _per_window(flow, events, "hmc", weights, alpha, border_ramp, flow_scaling, upsampling, reference_times,
                       at_normalisation)


# at_loss repeats hmc_loss's keyword-only options (less lambda_1 and alpha), so that each
# signature says what its loss takes.
def at_loss(
    flow: FlowInput,
    events: EventBatch,
    *,
    flow_scaling: float | None = None,
    lambda_2: float = LossSpec.lambda_2,
    border_penalty: float | torch.Tensor = 0.0,
    border_ramp: float = LossSpec.border_ramp,
    upsampling: Upsampling = "bilinear",
    reference_times: ReferenceTimes = "window",
    at_normalisation: AtNormalisation = "event_pixels",
) -> LossOutput:
    """Baseline loss "L_AT": ``L_AT(0) + L_AT(1) + lambda_2 L_smooth`` (same args as hmc_loss).
    ``components["ec"]`` is still reported (detached, the default alpha) for logging."""
    weights = {"lambda_2": lambda_2, "border_penalty": border_penalty}
    return _per_window(flow, events, "at", weights, LossSpec.alpha, border_ramp, flow_scaling, upsampling,
                       reference_times, at_normalisation)


def accumulated_hmc_loss(
    flows: Sequence[FlowInput],
    events_list: Sequence[EventBatch],
    *,
    flow_scaling: float | None = None,
    lambda_1: float = LossSpec.lambda_1,
    lambda_2: float = LossSpec.lambda_2,
    alpha: float = LossSpec.alpha,
    border_penalty: float | torch.Tensor = 0.0,
    outside_weight: float | torch.Tensor = 0.0,
    border_ramp: float = LossSpec.border_ramp,
    upsampling: Upsampling = "bilinear",
    reference_times: ReferenceTimes = "window",
    at_normalisation: AtNormalisation = "event_pixels",
) -> LossOutput:
    """Accumulated-window variant (docs/method.md, "Losses", Hagenaars "sequential learning").

    flows: K items, the flow of window k: a tensor (B, 2, H, W), pixels per window at full
        resolution, or a list of scales (as ``hmc_loss`` takes; every window the same number of
        scales), each brought to full resolution with ``upsampling``.
    events_list: K EventBatch, window k's events. Event i of window k has time T_i = k + tau_i
    (in windows) and is warped with its own window's flow: ``x' = x + (s - T_i) u_k(x)`` for
    references s in {0, K}; its timestamp weight is ``1 - |s - T_i| / K`` (so T_P stays in
    [0, 1]). L_AT(0) + L_AT(K) + lambda_1 (L_EC(0) + L_EC(K)) + lambda_2 * mean over k of
    L_smooth(flow k, window k's event pixels). With several scales: that loss for each scale
    (scale j of every window together) averaged over scales. With K = 1 this equals ``hmc_loss``.
    outside_weight (float or (B,) tensor): adds ``outside_weight * outside_distance / max(H, W)``
    (mean distance in pixels by which warped events lie outside the image, see
    ``warp.outside_distance``; for several scales, the mean over scales), a slope back into the
    frame for a net whose events all left it, where the border penalty alone is flat.
    ``components["outside_px"]`` reports the distance.
    border_ramp, upsampling, at_normalisation: as in ``hmc_loss``. reference_times: "window"
    (0 and K) or "events" (the first event of the first window and the last of the last).
    """
    weights = {"lambda_1": lambda_1, "lambda_2": lambda_2, "border_penalty": border_penalty}
    return _accumulated(flows, events_list, weights, alpha, border_ramp, outside_weight, flow_scaling, upsampling,
                        reference_times, at_normalisation)


def _accumulated_scales(flows, events_list, upsampling) -> list[list[torch.Tensor]]:
    """Every window's flows at full resolution, [window][scale], after checking the windows agree."""
    if len(flows) == 0 or len(flows) != len(events_list):
        raise ValueError(
            f"accumulated_hmc_loss: need K >= 1 flows and K event batches, got {len(flows)} "
            f"and {len(events_list)}"
        )
    scales = [to_full_resolution(f, upsampling) for f in flows]  # [window][scale]
    if any(len(s) != len(scales[0]) for s in scales):
        raise ValueError(f"accumulated_hmc_loss: windows give different numbers of scales {[len(s) for s in scales]}")
    for k, per_window in enumerate(scales):
        if per_window[0].shape != scales[0][0].shape:
            raise ValueError(f"flows[{k}] has shape {tuple(per_window[0].shape)} != flows[0] "
                             f"{tuple(scales[0][0].shape)}")
    B = scales[0][0].shape[0]
    for k, ev in enumerate(events_list):
        check_events(ev, batch_size=B, name=f"events_list[{k}]")
    return scales


def _accumulated(flows, events_list, weights: Mapping[str, Weight], alpha, border_ramp, outside_weight, flow_scaling,
                 upsampling="bilinear", reference_times="window", at_normalisation="event_pixels") -> LossOutput:
    """L_HMC over the events of K windows (``accumulated_hmc_loss``), its terms weighed by ``weights``."""
    _check_choice("reference_times", reference_times, REFERENCE_TIMES)
    _check_choice("at_normalisation", at_normalisation, AT_NORMALISATIONS)
    events_list = list(events_list)
    scales = _accumulated_scales(flows, events_list, upsampling)
    B, _, H, W = scales[0][0].shape
    events_list = [ev.zero_padding() for ev in events_list]  # as in _per_window
    K = len(scales)
    scaling = float(max(H, W)) if flow_scaling is None else float(flow_scaling)
    ramp = check_border_ramp(border_ramp)
    cat = lambda name: torch.cat([getattr(ev, name) for ev in events_list], dim=1)  # noqa: E731
    x, y, p, mask = cat("x"), cat("y"), cat("p"), cat("mask")
    dtype = scales[0][0].dtype
    masks = [event_pixel_mask(ev.x, ev.y, ev.mask, H, W) for ev in events_list]
    per_scale, distances = [], []
    for j in range(len(scales[0])):
        window_flows = [per_window[j] for per_window in scales]
        u = torch.cat([sample_flow(f, ev.x, ev.y, ev.mask) for f, ev in zip(window_flows, events_list)], dim=1)
        t = torch.cat([ev.tau.to(dtype) + k for k, ev in enumerate(events_list)], dim=1)
        if reference_times == "events":
            t, u = rebase_to_events(t, u, mask, float(K))
        accumulated = EventBatch(x, y, t, p, mask)  # tau: time in windows, k + tau
        inputs = TermInputs(accumulated, u, window_flows, masks, H, W, (0.0, float(K)), float(K), alpha, scaling, ramp,
                            at_normalisation)
        per_scale.append(term_values(inputs, "hmc", weights))
        if isinstance(outside_weight, torch.Tensor) or outside_weight:
            distances.append(outside_distance(accumulated, u, H, W, (0.0, float(K))))
    per_sample, components = combine_terms(per_scale, "hmc", weights)
    if distances:
        distance = sum(distances) / len(distances)
        per_sample = per_sample + outside_weight * distance / max(H, W)
        components = {**components, "outside_px": distance.detach()}
    return _output(per_sample, components)
