"""Charbonnier smoothness prior on the flow, where there are events (docs/method.md, "Losses").

Per-component form: for each of 4 neighbour directions (right, down, down-right, up-right) and
each flow component, ``rho(d) = sqrt(d^2 + eps^2)`` of the neighbour difference d of the flow in
network units (u / flow_scaling), summed over pairs whose two pixels both hold an input event
and over both components, then averaged over the 4 directions. (Hagenaars' code squares the sum
of the x and y differences instead; we take the per-component form.)
"""

from __future__ import annotations

import numpy as np
import torch

from . import _kernels  # compiled CPU kernels; set to None (tests do) for the torch reference path
from .kernel_switch import use_cpu_kernels

__all__ = ["event_pixel_mask", "charbonnier_smoothness"]


def event_pixel_mask(
    x: torch.Tensor, y: torch.Tensor, mask: torch.Tensor, height: int, width: int
) -> torch.Tensor:
    """Pixels holding at least one (unwarped) valid event.

    x, y: (B, N) float pixels; mask: (B, N) bool. Returns (B, height, width) bool.
    Coordinates are rounded to the nearest pixel (``torch.round``, ties to even), which is the
    identity for raw integer events and nearest-pixel for rectified float ones; events that
    round outside the image are ignored.
    """
    if _kernels is not None and use_cpu_kernels(x):
        out = np.zeros((x.shape[0], height, width), np.bool_)
        _kernels.event_mask_kernel(_kernels.use_threads())(
            np.ascontiguousarray(x.numpy()), np.ascontiguousarray(y.numpy(), dtype=x.numpy().dtype),
            np.ascontiguousarray(mask.numpy()), out)
        return torch.from_numpy(out)
    B, N = x.shape
    xi = torch.round(x).long()
    yi = torch.round(y).long()
    keep = mask & (xi >= 0) & (xi < width) & (yi >= 0) & (yi < height)
    hw = height * width
    flat = torch.arange(B, device=x.device).view(B, 1) * hw + yi * width + xi
    flat = torch.where(keep, flat, B * hw)  # dump slot for dropped events
    out = torch.zeros(B * hw + 1, dtype=torch.bool, device=x.device)
    out[flat.reshape(-1)] = True
    return out[:-1].view(B, height, width)


_DIRECTIONS = ((0, 1), (1, 0), (1, 1), (-1, 1))  # (d_row, d_col): right, down, down-right, up-right


def neighbour_pairs(event_mask: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """All neighbour pairs (4 directions) whose two pixels both hold an event.

    event_mask: (B, H, W) bool. Returns (first, second, batch), each (P,) int64: flat indices
    ``b * H * W + row * W + col`` of the two pixels of each pair, and the pair's batch element.
    """
    B, H, W = event_mask.shape
    firsts = []
    for dr, dc in _DIRECTIONS:
        r0, r1 = max(0, -dr), H - max(0, dr)  # rows of the first pixel with a neighbour
        a = event_mask[:, r0:r1, : W - dc]
        b = event_mask[:, r0 + dr : r1 + dr, dc:]
        bi, ri, ci = (a & b).nonzero(as_tuple=True)
        firsts.append((bi * H + ri + r0) * W + ci)
    counts = [f.numel() for f in firsts]
    first = torch.cat(firsts)
    step = torch.cat([torch.full((n,), dr * W + dc, dtype=torch.long, device=first.device)
                      for n, (dr, dc) in zip(counts, _DIRECTIONS)])
    return first, first + step, first // (H * W)


class _Charbonnier(torch.autograd.Function):
    """Per batch element: sum over pairs and components of sqrt(d^2 + eps^2); backward d / rho."""

    @staticmethod
    def forward(ctx, f, first, second, batch, eps):
        B, _, H, W = f.shape
        hw = H * W
        flat = f.reshape(-1)  # index b * 2HW + c * HW + pixel
        pix = first % hw
        ia = torch.stack([batch * (2 * hw) + pix, batch * (2 * hw) + pix + hw])  # (2, P)
        ib = ia + (second - first)
        d = flat.index_select(0, ib.view(-1)) - flat.index_select(0, ia.view(-1))
        d = d.view(2, -1)  # (2, P)
        rho = torch.hypot(d, d.new_tensor(eps))
        total = f.new_zeros(B).index_add_(0, batch, rho.sum(dim=0))
        ctx.save_for_backward(ia, ib, d / rho)
        ctx.shape = f.shape
        return total

    @staticmethod
    def backward(ctx, grad_total):
        ia, ib, slope = ctx.saved_tensors
        hw = ctx.shape[2] * ctx.shape[3]
        g = slope * grad_total[ia[0] // (2 * hw)]
        grad = slope.new_zeros(ctx.shape).view(-1)
        grad.index_add_(0, ib.view(-1), g.view(-1)).index_add_(0, ia.view(-1), -g.view(-1))
        return grad.view(ctx.shape), None, None, None, None


class _CharbonnierCompiled(torch.autograd.Function):
    """The same sum as ``_Charbonnier`` through one fused loop per batch element (numba, CPU)."""

    @staticmethod
    def forward(ctx, f, event_mask, eps, flow_scaling):
        np_dtype = np.float64 if f.dtype == torch.float64 else np.float32
        arrays = (np.ascontiguousarray(f.detach().numpy(), dtype=np_dtype), np.ascontiguousarray(event_mask.numpy()),
                  np.array([eps, 1.0 / flow_scaling], np_dtype))
        total = np.empty((f.shape[0], 2), np.float64)
        fwd, _ = _kernels.smoothness_kernels(_kernels.use_threads())
        fwd(*arrays, total)
        ctx.arrays = arrays
        return torch.from_numpy(total.sum(axis=1)).to(f.dtype)

    @staticmethod
    def backward(ctx, grad_total):
        f = ctx.arrays[0]
        grad = np.empty_like(f)
        _, bwd = _kernels.smoothness_kernels(_kernels.use_threads())
        bwd(*ctx.arrays, np.ascontiguousarray(grad_total.detach().numpy(), dtype=f.dtype), grad)
        return torch.from_numpy(grad), None, None, None


def charbonnier_smoothness(
    flow: torch.Tensor, event_mask: torch.Tensor, flow_scaling: float, eps: float = 1e-3
) -> torch.Tensor:
    """L_smooth per batch element.

    flow: (B, 2, H, W) float, pixels per window. event_mask: (B, H, W) bool (see
    ``event_pixel_mask``). flow_scaling: pixels per network unit (default in the losses:
    max(H, W)). eps: Charbonnier epsilon, 1e-3.
    Returns (B,) float: sum over counted pairs and both components of sqrt(d^2 + eps^2),
    averaged over the 4 directions. Differentiable in flow (fused backward, d rho/d d = d/rho).
    Cost is proportional to the number of counted pairs, not to the image size.
    """
    if _kernels is not None and use_cpu_kernels(flow):
        return _CharbonnierCompiled.apply(flow, event_mask, float(eps), float(flow_scaling)) / 4
    first, second, batch = neighbour_pairs(event_mask)
    return _Charbonnier.apply(flow / flow_scaling, first, second, batch, float(eps)) / 4
