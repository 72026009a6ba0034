"""Hybrid motion-compensation loss L_HMC (docs/method.md, "Losses", eq. 17) and the baseline L_AT.

A composite that is only a weighted sum:
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
window's zero-flow loss, so that pushing events out never pays, however dense the window).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal, Sequence, get_args

import torch
import torch.nn.functional as F

from ._validation import check_events, check_flow
from .events import EventBatch
from .image_terms import AT_NORMALISATIONS, AtNormalisation, event_image_terms
from .sampling import sample_flow
from .smoothness import charbonnier_smoothness, event_pixel_mask
from .warp import beyond_image, outside_distance, warp_events

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

#: The border rule's ramp (pixels) that the env's reward and the learner use by default
#: (docs/results.md, fifth round); the loss functions themselves default to 0 (the plain share).
BORDER_RAMP = 16.0

FlowInput = torch.Tensor | Sequence[torch.Tensor]


@dataclass(frozen=True)
class LossWeights:
    """The weights of L_HMC (eq. 17) and of the border rule (docs/method.md, "Losses").

    The defaults are the env's reward: the paper's lambda_1, lambda_2 and alpha, with the
    project's border rule on. Every other default of these weights is read from here."""

    lambda_1: float = 1.0
    """weight of the event-count term L_EC"""
    lambda_2: float = 1e-3
    """weight of the smoothness term"""
    alpha: float = 0.6
    """Charbonnier exponent of the smoothness term"""
    border_penalty: float = 1.0
    """border rule: x the window's zero-flow loss x the share of its events pushed out of the image"""
    border_ramp: float = BORDER_RAMP
    """the border rule's ramp, pixels beyond the border (0: the plain share)"""

    def of(self, loss: Literal["hmc", "at"]) -> dict:
        """The keyword arguments of ``hmc_loss`` / ``at_loss`` (the border penalty is per window:
        :func:`border_rule_weight`)."""
        _check_choice("loss", loss, ("hmc", "at"))
        weights = {"lambda_2": self.lambda_2, "border_ramp": self.border_ramp}
        return {**weights, "lambda_1": self.lambda_1, "alpha": self.alpha} if loss == "hmc" else weights


def border_rule_weight(loss_fn, zero_flow: torch.Tensor, events: EventBatch, border_penalty: float, **loss_kwargs):
    """The border rule's weight of each window: ``border_penalty`` x the window's loss under zero
    flow (``loss_fn(zero_flow, events, **loss_kwargs)``, no graph), (B,); 0.0 when the penalty is
    0. The loss charges this weight x the (ramped) share of the window's events pushed out."""
    if not border_penalty:
        return 0.0
    with torch.no_grad():
        return border_penalty * loss_fn(zero_flow, events, **loss_kwargs).per_sample


@dataclass(frozen=True)
class LossOutput:
    """loss: () scalar, mean of ``per_sample``. per_sample: (B,) loss per window (graph kept).
    components: (B,) detached tensors, averaged over scales: "at" = L_AT(0) + L_AT(1),
    "ec" = L_EC(0) + L_EC(1), "smooth" = L_smooth, "kept" = share of valid events' splat weight
    inside the image (mean over reference times; 1 for an empty window)."""

    loss: torch.Tensor
    per_sample: torch.Tensor
    components: dict


def _check_choice(name: str, value, allowed: tuple) -> None:
    if value not in allowed:
        raise ValueError(f"{name} must be one of {allowed}, got {value!r}")


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


def _terms(
    events: EventBatch, u, flow_for_smooth: Sequence[torch.Tensor], masks_for_smooth,
    height, width, references, span, alpha, flow_scaling, need_ec, border_ramp=0.0,
    at_normalisation: AtNormalisation = "event_pixels",
) -> dict:
    """(B,) tensors at, ec, smooth, dropped for one set of (possibly accumulated) events; their
    ``tau`` is the time in windows (k + tau for window k of K accumulated ones)."""
    at, ec, kept = event_image_terms(events, u, height, width, references, span, alpha, at_normalisation)
    at = at.sum(dim=1)  # L_AT(s0) + L_AT(s1)
    ec = ec.sum(dim=1) if need_ec else ec.sum(dim=1).detach()
    n_valid = events.mask.sum(dim=1).to(u.dtype)  # (B,)
    kept = kept / n_valid.clamp_min(1).unsqueeze(1)  # (B, R) share of splat weight kept
    dropped = torch.where(n_valid.unsqueeze(1) > 0, 1 - kept, torch.zeros_like(kept))
    if border_ramp > 0:
        charge = ramped_dropped_share(events, u, height, width, references, border_ramp)
    else:
        charge = dropped
    smooth = sum(
        charbonnier_smoothness(f, m, flow_scaling) for f, m in zip(flow_for_smooth, masks_for_smooth)
    ) / len(flow_for_smooth)
    return {"at": at, "ec": ec, "smooth": smooth, "dropped": dropped, "charge": charge}


def _combine(terms_per_scale, lambda_1, lambda_2, border_penalty, use_ec) -> LossOutput:
    per = []
    for tm in terms_per_scale:
        s = tm["at"] + lambda_2 * tm["smooth"]
        if use_ec:
            s = s + lambda_1 * tm["ec"]
        if isinstance(border_penalty, torch.Tensor) or border_penalty:
            s = s + border_penalty * tm["charge"].sum(dim=1)
        per.append(s)
    n = len(terms_per_scale)
    per_sample = sum(per) / n
    comps = {
        k: (sum(tm[k] for tm in terms_per_scale) / n).detach() for k in ("at", "ec", "smooth")
    }
    comps["kept"] = (1 - sum(tm["dropped"] for tm in terms_per_scale) / n).mean(dim=1).detach()
    return LossOutput(loss=per_sample.mean(), per_sample=per_sample, components=comps)


def _per_window(flow, events, flow_scaling, lambda_1, lambda_2, alpha, border_penalty, use_ec,
                border_ramp=0.0, upsampling="bilinear", reference_times="window", at_normalisation="event_pixels"):
    _check_choice("reference_times", reference_times, REFERENCE_TIMES)
    _check_choice("at_normalisation", at_normalisation, AT_NORMALISATIONS)
    flows = to_full_resolution(flow, upsampling)
    B, _, H, W = flows[0].shape
    check_events(events, batch_size=B)
    events = events.zero_padding()  # padding may hold anything; the torch path reads every slot
    scaling = float(max(H, W)) if flow_scaling is None else float(flow_scaling)
    ramp = check_border_ramp(border_ramp)
    ev_mask = event_pixel_mask(events.x, events.y, events.mask, H, W)
    terms = []
    for f in flows:
        u = sample_flow(f, events.x, events.y, events.mask)
        t = events.tau
        if reference_times == "events":
            t, u = rebase_to_events(t.to(u.dtype), u, events.mask, 1.0)
        terms.append(
            _terms(events._replace(tau=t), u, [f], [ev_mask], H, W, (0.0, 1.0), 1.0, alpha, scaling, use_ec, ramp,
                   at_normalisation)
        )
    return _combine(terms, lambda_1, lambda_2, border_penalty, use_ec)


def check_border_ramp(border_ramp) -> float:
    """The ramp as a float; ValueError unless it is a finite number of pixels >= 0."""
    ramp = float(border_ramp)
    if not ramp >= 0 or ramp == float("inf"):
        raise ValueError(f"border_ramp must be a finite number of pixels >= 0, got {border_ramp!r}")
    return ramp


def hmc_loss(
    flow: FlowInput,
    events: EventBatch,
    *,
    flow_scaling: float | None = None,
    lambda_1: float = LossWeights.lambda_1,
    lambda_2: float = LossWeights.lambda_2,
    alpha: float = LossWeights.alpha,
    border_penalty: float | torch.Tensor = 0.0,
    border_ramp: float = 0.0,
    upsampling: Upsampling = "bilinear",
    reference_times: ReferenceTimes = "window",
    at_normalisation: AtNormalisation = "event_pixels",
) -> LossOutput:
    """Hybrid motion-compensation loss, eq. 17, per window.

    flow: (B, 2, H, W) float, pixels of displacement over the window at full sensor resolution,
        or a list of such tensors at several resolutions (see ``to_full_resolution``).
    events: EventBatch of B windows (x, y pixels; tau in [0, 1]; padded with mask).
    flow_scaling: pixels per network unit for the smoothness term; default max(H, W).
    lambda_1, lambda_2, alpha: defaults from :class:`LossWeights` (the paper's). border_penalty: 0 (paper), or the
    weight (float, or (B,) tensor per window) of ``sum_s (1 - kept_s)`` (see the module doc).
    border_ramp: pixels; > 0 charges each event's dropped share times ``min(1, d / border_ramp)``,
    d = how far beyond the image it lands (``ramped_dropped_share``); 0: the plain share.
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
    return _per_window(flow, events, flow_scaling, lambda_1, lambda_2, alpha, border_penalty, True,
                       border_ramp, upsampling, reference_times, at_normalisation)


# at_loss repeats hmc_loss's keyword-only options (less lambda_1 and alpha), so that each
# signature says what its loss takes.
def at_loss(
    flow: FlowInput,
    events: EventBatch,
    *,
    flow_scaling: float | None = None,
    lambda_2: float = LossWeights.lambda_2,
    border_penalty: float | torch.Tensor = 0.0,
    border_ramp: float = 0.0,
    upsampling: Upsampling = "bilinear",
    reference_times: ReferenceTimes = "window",
    at_normalisation: AtNormalisation = "event_pixels",
) -> LossOutput:
    """Baseline loss "L_AT": ``L_AT(0) + L_AT(1) + lambda_2 L_smooth`` (same args as hmc_loss).
    ``components["ec"]`` is still reported (detached, the default alpha) for logging."""
    return _per_window(flow, events, flow_scaling, LossWeights.lambda_1, lambda_2, LossWeights.alpha, border_penalty,
                       False, border_ramp, upsampling, reference_times, at_normalisation)


def accumulated_hmc_loss(
    flows: Sequence[FlowInput],
    events_list: Sequence[EventBatch],
    *,
    flow_scaling: float | None = None,
    lambda_1: float = LossWeights.lambda_1,
    lambda_2: float = LossWeights.lambda_2,
    alpha: float = LossWeights.alpha,
    border_penalty: float | torch.Tensor = 0.0,
    outside_weight: float | torch.Tensor = 0.0,
    border_ramp: float = 0.0,
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
    _check_choice("reference_times", reference_times, REFERENCE_TIMES)
    _check_choice("at_normalisation", at_normalisation, AT_NORMALISATIONS)
    events_list = list(events_list)
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
    B, _, H, W = scales[0][0].shape
    for k, ev in enumerate(events_list):
        check_events(ev, batch_size=B, name=f"events_list[{k}]")
    events_list = [ev.zero_padding() for ev in events_list]  # as in _per_window
    K = len(scales)
    scaling = float(max(H, W)) if flow_scaling is None else float(flow_scaling)
    ramp = check_border_ramp(border_ramp)
    cat = lambda name: torch.cat([getattr(ev, name) for ev in events_list], dim=1)  # noqa: E731
    x, y, p, mask = cat("x"), cat("y"), cat("p"), cat("mask")
    dtype = scales[0][0].dtype
    masks = [event_pixel_mask(ev.x, ev.y, ev.mask, H, W) for ev in events_list]
    terms, distances = [], []
    for j in range(len(scales[0])):
        window_flows = [per_window[j] for per_window in scales]
        u = torch.cat([sample_flow(f, ev.x, ev.y, ev.mask) for f, ev in zip(window_flows, events_list)], dim=1)
        t = torch.cat([ev.tau.to(dtype) + k for k, ev in enumerate(events_list)], dim=1)
        if reference_times == "events":
            t, u = rebase_to_events(t, u, mask, float(K))
        accumulated = EventBatch(x, y, t, p, mask)  # tau: time in windows, k + tau
        terms.append(_terms(accumulated, u, window_flows, masks, H, W, (0.0, float(K)), float(K), alpha,
                            scaling, True, ramp, at_normalisation))
        if isinstance(outside_weight, torch.Tensor) or outside_weight:
            distances.append(outside_distance(accumulated, u, H, W, (0.0, float(K))))
    out = _combine(terms, lambda_1, lambda_2, border_penalty, True)
    if distances:
        distance = sum(distances) / len(distances)
        per_sample = out.per_sample + outside_weight * distance / max(H, W)
        out = LossOutput(loss=per_sample.mean(), per_sample=per_sample,
                         components={**out.components, "outside_px": distance.detach()})
    return out
