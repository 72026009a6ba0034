"""Flow metrics (docs/method.md, "Metrics"): AEE and outlier %, FWL, RSAT.

Numpy in, float out (``flow_error``, ``fwl``, ``rsat``), computed in float64 by the torch
versions (``*_torch``, batched, usable on CUDA during training, no gradients needed).
"""

from __future__ import annotations

import numpy as np
import torch

from ._validation import check_events, check_flow
from .events import EventBatch
from .sampling import sample_flow
from .warp import warp_events

__all__ = ["dense_flow_error", "dense_flow_error_torch", "flow_error", "flow_error_torch", "fwl", "fwl_torch",
           "rsat", "rsat_torch"]


def _central_crop(a: torch.Tensor, crop) -> torch.Tensor:
    if crop is None:
        return a
    ch, cw = (int(c) for c in crop)
    H, W = a.shape[-2:]
    if not (0 < ch <= H and 0 < cw <= W):
        raise ValueError(f"crop {tuple(crop)} does not fit in the image ({H}, {W})")
    top, left = (H - ch) // 2, (W - cw) // 2
    return a[..., top:top + ch, left:left + cw]


def flow_error_torch(
    flow: torch.Tensor,
    flow_gt: torch.Tensor,
    valid_gt: torch.Tensor | None,
    event_mask: torch.Tensor | None,
    *,
    dt_ratio: float = 1.0,
    crop: tuple[int, int] | None = None,
) -> dict:
    """AEE and outlier share per batch element.

    flow, flow_gt: (B, 2, H, W) float, pixels (flow over the input window; gt over its own
    interval). valid_gt: (B, H, W) bool, or None for "not both gt components are 0" (MVSEC
    rule). event_mask: (B, H, W) bool, pixels with at least one input event, or None for all.
    dt_ratio: dt_gt / dt_input, the flow is multiplied by it (linear motion). crop: (h, w)
    central crop or None.
    Returns dict of (B,) tensors: "aee" (pixels), "outlier_pct" (%, error > 3 px AND > 5 % of
    the GROUND-TRUTH magnitude; Hagenaars' code uses the predicted magnitude), "n_pixels"
    (int64). Elements with no counted pixel get aee = outlier_pct = NaN.
    """
    if flow.shape != flow_gt.shape or flow.ndim != 4 or flow.shape[1] != 2:
        raise ValueError(
            f"flow {tuple(flow.shape)} and flow_gt {tuple(flow_gt.shape)} must both be (B, 2, H, W)"
        )
    B, _, H, W = flow.shape
    for name, m in (("valid_gt", valid_gt), ("event_mask", event_mask)):
        if m is not None and tuple(m.shape) != (B, H, W):
            raise ValueError(f"{name} has shape {tuple(m.shape)}, expected {(B, H, W)}")
    if not bool(torch.isfinite(flow).all()):
        raise ValueError("flow contains NaN or inf")
    if valid_gt is None:
        valid_gt = (flow_gt != 0).any(dim=1)
    valid = valid_gt.bool() & torch.isfinite(flow_gt).all(dim=1)
    if event_mask is not None:
        valid = valid & event_mask.bool()
    err = torch.linalg.vector_norm(flow * dt_ratio - flow_gt, dim=1)  # (B, H, W)
    mag = torch.linalg.vector_norm(flow_gt, dim=1)
    err, mag, valid = (_central_crop(a, crop) for a in (err, mag, valid))
    err = torch.where(valid, err, torch.zeros_like(err))
    n = valid.sum(dim=(1, 2))
    outlier = valid & (err > 3.0) & (err > 0.05 * mag)
    nf = n.to(err.dtype)
    nan = torch.full_like(nf, float("nan"))
    aee = torch.where(n > 0, err.sum(dim=(1, 2)) / nf.clamp_min(1), nan)
    pct = torch.where(n > 0, 100.0 * outlier.sum(dim=(1, 2)).to(err.dtype) / nf.clamp_min(1), nan)
    return {"aee": aee, "outlier_pct": pct, "n_pixels": n}


# The numpy face of flow_error_torch: the same arguments for one map instead of a batch.
def flow_error(
    flow: np.ndarray,
    flow_gt: np.ndarray,
    valid_gt: np.ndarray | None,
    event_mask: np.ndarray | None,
    *,
    dt_ratio: float = 1.0,
    crop: tuple[int, int] | None = None,
) -> dict:
    """AEE and outlier % of one flow map (see ``flow_error_torch`` for the definitions).

    flow, flow_gt: (2, H, W) float pixels; valid_gt, event_mask: (H, W) bool or None.
    Returns dict(aee=float, outlier_pct=float, n_pixels=int); NaNs when n_pixels == 0.
    """
    t = lambda a: None if a is None else torch.as_tensor(np.asarray(a)).unsqueeze(0)  # noqa: E731
    out = flow_error_torch(
        t(flow).double(), t(flow_gt).double(), t(valid_gt), t(event_mask),
        dt_ratio=dt_ratio, crop=crop,
    )
    return {"aee": float(out["aee"][0]), "outlier_pct": float(out["outlier_pct"][0]),
            "n_pixels": int(out["n_pixels"][0])}


def dense_flow_error_torch(flow: torch.Tensor, flow_gt: torch.Tensor, valid_gt: torch.Tensor) -> dict:
    """The DSEC benchmark's scores per batch element: every pixel with valid ground truth counts,
    with or without events (no event mask).

    flow, flow_gt: (B, 2, H, W) float, pixels of displacement over the same interval.
    valid_gt: (B, H, W) bool. Returns dict of (B,) tensors: "epe" (mean endpoint error, px),
    "1pe" / "2pe" / "3pe" (% of pixels with endpoint error > 1 / 2 / 3 px), "ae" (mean angular
    error in degrees between the space-time vectors (u, v, 1) and (u_gt, v_gt, 1), Barron et al.
    1994), "n_pixels" (int64). Elements without a valid pixel get NaN scores.
    """
    if flow.shape != flow_gt.shape or flow.ndim != 4 or flow.shape[1] != 2:
        raise ValueError(f"flow {tuple(flow.shape)} and flow_gt {tuple(flow_gt.shape)} must both be (B, 2, H, W)")
    B, _, H, W = flow.shape
    if tuple(valid_gt.shape) != (B, H, W):
        raise ValueError(f"valid_gt has shape {tuple(valid_gt.shape)}, expected {(B, H, W)}")
    if not bool(torch.isfinite(flow).all()):
        raise ValueError("flow contains NaN or inf")
    valid = valid_gt.bool() & torch.isfinite(flow_gt).all(dim=1)
    gt = torch.where(valid.unsqueeze(1), flow_gt, torch.zeros_like(flow_gt))
    epe = torch.linalg.vector_norm(flow - gt, dim=1)
    dot = (flow * gt).sum(dim=1) + 1.0
    norms = torch.sqrt(((flow * flow).sum(dim=1) + 1.0) * ((gt * gt).sum(dim=1) + 1.0))
    ae = torch.rad2deg(torch.arccos(torch.clamp(dot / norms, -1.0, 1.0)))
    n = valid.sum(dim=(1, 2))
    nf = n.to(epe.dtype).clamp_min(1)
    nan = torch.full_like(nf, float("nan"))

    def mean(values: torch.Tensor) -> torch.Tensor:
        return torch.where(n > 0, torch.where(valid, values, torch.zeros_like(values)).sum(dim=(1, 2)) / nf, nan)

    out = {"epe": mean(epe), "ae": mean(ae)}
    for k in (1, 2, 3):
        out[f"{k}pe"] = 100.0 * mean((epe > k).to(epe.dtype))
    out["n_pixels"] = n
    return out


def dense_flow_error(flow: np.ndarray, flow_gt: np.ndarray, valid_gt: np.ndarray) -> dict:
    """DSEC scores of one flow map (see ``dense_flow_error_torch``): flow, flow_gt (2, H, W)
    float pixels, valid_gt (H, W) bool -> dict of floats (epe, 1pe, 2pe, 3pe, ae) and n_pixels."""
    t = lambda a: torch.as_tensor(np.asarray(a)).unsqueeze(0)  # noqa: E731
    out = dense_flow_error_torch(t(flow).double(), t(flow_gt).double(), t(valid_gt))
    return {k: (int(v[0]) if k == "n_pixels" else float(v[0])) for k, v in out.items()}


def _nearest_images(flow: torch.Tensor, events: EventBatch, values: torch.Tensor) -> torch.Tensor:
    """Events warped to s = 1 and splatted to the nearest pixel (torch.round), off-image dropped.

    flow: (B, 2, H, W); values: (B, N, C). Returns (B, C, H, W).
    """
    B, _, H, W = flow.shape
    u = sample_flow(flow, events.x, events.y)
    xw, yw = warp_events(events.x.to(flow.dtype), events.y.to(flow.dtype),
                         events.tau.to(flow.dtype), u, 1.0)
    xi, yi = torch.round(xw).long(), torch.round(yw).long()
    keep = events.mask & (xi >= 0) & (xi < W) & (yi >= 0) & (yi < H)
    idx = torch.arange(B, device=flow.device).view(B, 1) * (H * W) + yi * W + xi
    idx = torch.where(keep, idx, 0)
    src = values * keep.unsqueeze(-1)
    C = values.shape[-1]
    out = values.new_zeros(B * H * W, C).index_add_(0, idx.reshape(-1), src.reshape(-1, C))
    return out.view(B, H, W, C).permute(0, 3, 1, 2)


def _ratio(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    return torch.where(b > 0, a / torch.where(b > 0, b, torch.ones_like(b)), torch.full_like(a, float("nan")))


@torch.no_grad()
def fwl_torch(flow: torch.Tensor, events: EventBatch) -> torch.Tensor:
    """Flow warp loss (Stoffregen 2020): Var(IWE with flow) / Var(IWE with zero flow).

    flow: (B, 2, H, W) float pixels per window; events: EventBatch of B windows.
    IWE = all valid events (both polarities) warped to s = 1, nearest-pixel splat; variance over
    all H*W pixels. Returns (B,) in flow's dtype; > 1 means the flow sharpens (higher is better);
    NaN where the zero-flow IWE has zero variance (e.g. an empty window).
    """
    check_flow(flow)
    check_events(events, batch_size=flow.shape[0])
    ones = torch.ones_like(events.x, dtype=flow.dtype).unsqueeze(-1)
    var = lambda f: _nearest_images(f, events, ones).flatten(1).var(dim=1, unbiased=False)  # noqa: E731
    return _ratio(var(flow), var(torch.zeros_like(flow)))


@torch.no_grad()
def rsat_torch(flow: torch.Tensor, events: EventBatch) -> torch.Tensor:
    """Ratio of squared average timestamps (Hagenaars): L_AT-style value with the flow divided by
    the same with zero flow, at s = 1 only, nearest-pixel splat (timestamp weight tau).

    flow: (B, 2, H, W) float pixels per window; events: EventBatch. Returns (B,); lower is
    better; NaN where the zero-flow value is 0 (empty window, or every event at tau = 0).
    """
    check_flow(flow)
    check_events(events, batch_size=flow.shape[0])
    on = (events.p > 0).to(flow.dtype)
    tau = events.tau.to(flow.dtype)
    values = torch.stack([on, on * tau, 1 - on, (1 - on) * tau], dim=-1)  # C+, A+, C-, A-

    def sat(f):
        img = _nearest_images(f, events, values)
        count, stamp = img[:, 0::2], img[:, 1::2]  # (B, 2, H, W)
        T = stamp / (count + 1e-9)
        nnz = (count.sum(dim=1) > 0).sum(dim=(1, 2)).to(f.dtype)
        return (T * T).sum(dim=(1, 2, 3)) / (nnz + 1e-9)

    return _ratio(sat(flow), sat(torch.zeros_like(flow)))


def _one_window(flow: np.ndarray, window, sensor_size) -> tuple:
    if not hasattr(window, "events"):
        raise TypeError(f"expected a Window (envs.windows.Window; Window.of(events, t_start, t_end) "
                        f"builds one from Events), got {type(window).__name__}")
    H, W = (int(s) for s in (window.sensor_size if sensor_size is None else sensor_size))
    flow = np.asarray(flow)
    if flow.shape != (2, H, W):
        raise ValueError(f"flow has shape {flow.shape}, expected (2, {H}, {W}) from sensor_size")
    ev = EventBatch.from_windows([window], dtype=torch.float64)
    return torch.as_tensor(flow, dtype=torch.float64).unsqueeze(0), ev


def fwl(flow: np.ndarray, window, sensor_size: tuple[int, int] | None = None) -> float:
    """FWL of one window (see ``fwl_torch``).

    flow: (2, H, W) float pixels per window. window: a :class:`~envs.windows.Window` (its events
    and ``[t_start, t_end)``). sensor_size: (H, W), the window's own where None. Returns a float
    (NaN for an empty window).
    """
    f, ev = _one_window(flow, window, sensor_size)
    return float(fwl_torch(f, ev)[0])


def rsat(flow: np.ndarray, window, sensor_size: tuple[int, int] | None = None) -> float:
    """RSAT of one window (see ``rsat_torch``); arguments as ``fwl``. NaN for an empty window."""
    f, ev = _one_window(flow, window, sensor_size)
    return float(rsat_torch(f, ev)[0])
