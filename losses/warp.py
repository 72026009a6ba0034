"""Warps: events to a reference time (eq. 12) and a flow field forward (eq. 9)."""

from __future__ import annotations

import numpy as np
import torch

from . import _kernels  # compiled CPU kernels; set to None (tests do) for the torch reference path
from .events import EventBatch
from .kernel_switch import use_cpu_kernels
from .splat import bilinear_splat

__all__ = ["warp_events", "forward_warp_flow", "outside_distance", "beyond_image", "HOLE_WEIGHT"]

#: Target pixels of the forward warp (eq. 9) whose splatted weight A0 is at most this are holes,
#: as zero-weight ones are. The backward divides by A0, so sources landing with a tiny total
#: weight (far corners of their splats) gave gradients growing as 1 / A0 without bound. 1e-5 of
#: one source's full weight: on the shipped models' rollouts no pixel lies in (0, 1e-5], so their
#: flows are unchanged (1e-4 already changed some), and the gradient's 1 / A0 stays below 1e5.
HOLE_WEIGHT = 1e-5


def warp_events(
    x: torch.Tensor, y: torch.Tensor, t: torch.Tensor, u: torch.Tensor, reference: float
) -> tuple[torch.Tensor, torch.Tensor]:
    """Move each event along its flow to the reference time (eq. 12).

    x, y: (...) float pixels; t: (...) float, event time in windows (tau, or k + tau in the
    accumulated variant); u: (..., 2) float, pixels per window; reference: s, in windows.
    Returns (x', y'), each (...): ``x' = x + (s - t) * u_x``, ``y' = y + (s - t) * u_y``.
    """
    dt = reference - t
    return x + dt * u[..., 0], y + dt * u[..., 1]


def beyond_image(xw: torch.Tensor, yw: torch.Tensor, height: int, width: int) -> torch.Tensor:
    """L1 distance (pixels) by which points (xw, yw) lie outside [0, W-1] x [0, H-1]; 0 inside."""
    return torch.relu(-xw) + torch.relu(xw - (width - 1)) + torch.relu(-yw) + torch.relu(yw - (height - 1))


def outside_distance(
    events: EventBatch,
    u: torch.Tensor,
    height: int,
    width: int,
    references: tuple[float, ...] = (0.0, 1.0),
) -> torch.Tensor:
    """How far warped events lie outside the image: (B,) mean over valid events and reference
    times of ``relu(-x') + relu(x' - (W-1)) + relu(-y') + relu(y' - (H-1))``, in pixels.

    events: B windows (tau: time in windows); u: (B, N, 2) pixels per window. 0 when every warped
    event stays inside; unlike the share of splat weight dropped at the border, it keeps a
    gradient that points back into the image however far the events went.
    """
    x, y, t, _, mask = events
    total = x.new_zeros(x.shape[0], dtype=u.dtype)
    m = mask.to(u.dtype)
    for s in references:
        xw, yw = warp_events(x.to(u.dtype), y.to(u.dtype), t.to(u.dtype), u, s)
        d = beyond_image(xw, yw, height, width) * m
        total = total + d.sum(dim=1)
    return total / (m.sum(dim=1).clamp_min(1) * len(references))


class _ForwardWarpCompiled(torch.autograd.Function):
    """The compiled CPU kernel of :func:`forward_warp_flow` (same arithmetic as its torch path)."""

    @staticmethod
    def forward(ctx, flow, min_weight):
        f = np.ascontiguousarray(flow.detach().numpy())
        B, _, H, W = f.shape
        threshold = f.dtype.type(min_weight)  # compared in the flow's dtype, as the torch path does
        splat, normalize, _, _ = _kernels.forward_warp_kernels(_kernels.use_threads())
        partial = np.empty((B, _kernels.warp_strips(B), H, W, 3), f.dtype)
        splat(f, partial)
        acc = np.empty((B, H, W, 3), f.dtype)
        out = np.empty_like(f)
        normalize(partial, acc, out, threshold)
        ctx.arrays = (f, acc, out)
        ctx.threshold = threshold
        return torch.from_numpy(out)

    @staticmethod
    def backward(ctx, grad_out):
        f, acc, out = ctx.arrays
        _, _, target_gradients, gather = _kernels.forward_warp_kernels(_kernels.use_threads())
        g = np.ascontiguousarray(grad_out.detach().numpy(), dtype=f.dtype)
        target = np.empty_like(acc)
        target_gradients(acc, out, g, target, ctx.threshold)
        grad = np.empty_like(f)
        gather(f, target, grad)
        return torch.from_numpy(grad), None


def forward_warp_flow(flow: torch.Tensor, min_weight: float = HOLE_WEIGHT) -> torch.Tensor:
    """Prior flow alignment of FGD-Net (eq. 9): ``ubar(x + u(x)) = u(x)``.

    flow: (B, 2, H, W) float, pixels per window at the flow's own resolution.
    min_weight: a target pixel whose splatted weight A0 is not above this is a hole
        (default :data:`HOLE_WEIGHT`; 0 keeps every pixel that receives any weight).
    Returns (B, 2, H, W): each pixel's flow vector bilinearly splatted to its displaced position,
    divided by the splatted weight A0 there; holes (A0 <= min_weight) are 0 and pass no
    gradient, so the backward's 1 / A0 stays below 1 / min_weight.
    Corners that land outside the image are dropped. Differentiable in flow.
    """
    if flow.ndim != 4 or flow.shape[1] != 2:
        raise ValueError(f"forward_warp_flow: flow must be (B, 2, H, W), got {tuple(flow.shape)}")
    min_weight = float(min_weight)
    if not min_weight >= 0:
        raise ValueError(f"forward_warp_flow: min_weight must be >= 0, got {min_weight!r}")
    if _kernels is not None and use_cpu_kernels(flow):
        return _ForwardWarpCompiled.apply(flow, min_weight)
    B, _, H, W = flow.shape
    rows, cols = torch.meshgrid(
        torch.arange(H, dtype=flow.dtype, device=flow.device),
        torch.arange(W, dtype=flow.dtype, device=flow.device),
        indexing="ij",
    )
    u = flow.flatten(2).transpose(1, 2)  # (B, HW, 2)
    x = cols.reshape(1, -1) + u[..., 0]
    y = rows.reshape(1, -1) + u[..., 1]
    values = torch.cat([torch.ones_like(u[..., :1]), u], dim=-1)  # (B, HW, 3): weight, u_x, u_y
    out = bilinear_splat(x, y, values, H, W)  # (B, 3, H, W)
    weight, moved = out[:, :1], out[:, 1:]
    hit = weight > min_weight  # holes: no weight, or too little to divide by (HOLE_WEIGHT)
    return torch.where(hit, moved / torch.where(hit, weight, torch.ones_like(weight)), 0.0)
