"""L_AT(s) and L_EC(s) straight from the events, with a fused analytic backward.

Same values as ``average_timestamp_loss(*warped_event_images(...))`` and
``event_count_loss(count)`` (the tests check both against a slow loop), computed with as few
passes over the big tensors as possible: the corner weights are written straight into the
scatter source (count and timestamp channels of every batch element, reference time and
polarity go out in one scatter_add), and the backward does not go through autograd's
temporaries: per pixel it forms dL/dC_P and dL/dA_P (eqs. 13-16), gathers them at each event's
4 corners (one gather, the adjoint of the scatter), and uses the separable kernel's derivative

    dL/dx' = sum_c G_c dk_c/dx',   G_c = dL/dC(q_c) + w_i dL/dA(q_c),

with dk/dx' = +-wy (right/left corners) and dk/dy' = +-wx (lower/upper corners). Then
dL/du_i = sum_s (s - t_i) dL/dx'_i(s) (eq. 12). This is the exact gradient of the same
piecewise-smooth function autograd would differentiate (N_nz is piecewise constant); the tests
check it with torch.autograd.gradcheck in float64.
"""

from __future__ import annotations

from typing import Literal, Sequence, get_args

import numpy as np
import torch

from . import _kernels  # compiled CPU kernels; set to None (tests do) for the torch reference path
from .events import EventBatch
from .iwe import warped_corners
from .kernel_switch import use_cpu_kernels
from .splat import crop_padding

__all__ = ["event_image_terms", "AtNormalisation", "AT_NORMALISATIONS"]

#: How L_AT(s) is normalised: by the pixels holding warped events (default), or eq. 14's bare sum.
AtNormalisation = Literal["event_pixels", "sum"]
AT_NORMALISATIONS = get_args(AtNormalisation)


def _zero_ring_(padded: torch.Tensor) -> torch.Tensor:
    padded[..., 0, :] = 0
    padded[..., -1, :] = 0
    padded[..., :, 0] = 0
    padded[..., :, -1] = 0
    return padded


class _EventImageTerms(torch.autograd.Function):
    @staticmethod
    def forward(ctx, u, events, height, width, references, span, alpha):
        B, N = events.x.shape
        R = len(references)
        dtype = u.dtype
        # eq. 12's warp and the splat corners, written straight into the scatter source
        index, wx, wy, inside, closeness, dt = warped_corners(events, u, height, width, references, span)
        src = torch.empty(B, R, 2, 4, N, dtype=dtype, device=u.device)  # [count, stamp] x corner
        k = src[:, :, 0]
        torch.mul(wy.unsqueeze(3), wx.unsqueeze(2), out=k.view(B, R, 2, 2, N))  # k = wy[a] wx[b]
        torch.mul(k, closeness.unsqueeze(2), out=src[:, :, 1])
        rows, hp, wp = B * R, height + 2, width + 2
        idx = index.view(rows, 1, 4 * N).expand(rows, 2, 4 * N)
        padded = torch.zeros(rows, 2, 2 * hp * wp, dtype=dtype, device=u.device)
        padded.scatter_add_(2, idx, src.view(rows, 2, 4 * N))
        padded = padded.view(B, R, 2, 2, hp, wp)  # (B, R, [count, stamp], [ON, OFF], H+2, W+2)
        images = crop_padding(padded)
        count, stamp = images[:, :, 0], images[:, :, 1]  # (B, R, 2, H, W)
        inv = torch.reciprocal(count + 1e-9)
        T = stamp * inv  # eq. 13
        n_nz = (count.sum(dim=2) > 0).sum(dim=(-2, -1)).to(dtype)  # pixels with C_+ + C_- > 0
        Z = n_nz + 1e-9
        at = torch.linalg.vector_norm(T, dim=(2, 3, 4)) ** 2 / Z  # eq. 14, normalised
        E = torch.exp(count * -alpha)
        S = E.sum(dim=(-2, -1))  # (B, R, 2), eq. 15
        ec = (height * width / S).sum(dim=-1) - 2  # eq. 16
        kept = count.sum(dim=(2, 3, 4))  # (B, R) splat weight inside the image
        ctx.save_for_backward(index, wx, wy, inside, closeness, dt, inv, T, E, S, Z)
        ctx.geometry = (height, width, alpha)
        ctx.mark_non_differentiable(kept, n_nz)
        ctx.set_materialize_grads(False)  # None for an unused output (e.g. ec in at_loss)
        return at, ec, kept, n_nz

    @staticmethod
    def backward(ctx, grad_at, grad_ec, _grad_kept, _grad_n_nz):
        index, wx, wy, inside, closeness, dt, inv, T, E, S, Z = ctx.saved_tensors
        height, width, alpha = ctx.geometry
        B, R, N = closeness.shape
        hp, wp = height + 2, width + 2
        grads = _zero_ring_(inv.new_empty(B, R, 2, 2, hp, wp))  # ring 0: dropped corners
        g_count, g_stamp = crop_padding(grads[:, :, 0]), crop_padding(grads[:, :, 1])
        if grad_at is None:
            grad_at = inv.new_zeros(B, R)
        # L_AT = sum T^2 / Z: dL/dA = 2 T / (C + 1e-9) / Z, dL/dC = -T dL/dA
        torch.mul(T * inv, (2 * grad_at / Z).view(B, R, 1, 1, 1), out=g_stamp)
        torch.mul(g_stamp, T, out=g_count).neg_()
        if grad_ec is not None:  # L_EC = sum_P HW / S_P - 2: dL/dC = alpha HW E / S^2
            scale = (alpha * height * width) * grad_ec.view(B, R, 1) / (S * S)
            g_count.addcmul_(E, scale.view(B, R, 2, 1, 1))
        rows = B * R
        idx = index.view(rows, 1, 4 * N).expand(rows, 2, 4 * N)
        gathered = grads.view(rows, 2, -1).gather(2, idx).view(B, R, 2, 2, 2, N)
        # G_c = dL/dC + w dL/dA at each corner, as (B, R, 2 [row a], 2 [col b], N)
        G = torch.addcmul(gathered[:, :, 0], gathered[:, :, 1], closeness.view(B, R, 1, 1, N))
        gx = ((G[:, :, :, 1] - G[:, :, :, 0]) * wy).sum(dim=2)  # dL/dx' (wy holds the inside mask)
        gy = ((G[:, :, 1] - G[:, :, 0]) * wx).sum(dim=2) * inside  # dL/dy'
        grad_u = torch.stack([(gx * dt).sum(dim=1), (gy * dt).sum(dim=1)], dim=-1)  # eq. 12
        return grad_u, None, None, None, None, None, None



class _EventImageTermsCompiled(torch.autograd.Function):
    """The same function as ``_EventImageTerms`` through the fused numba kernels (CPU only)."""

    @staticmethod
    def forward(ctx, u, events, height, width, references, span, alpha):
        x, y, t, p, mask = events
        B, N = x.shape
        R = len(references)
        dtype = u.dtype
        np_dtype = np.float64 if dtype == torch.float64 else np.float32
        arrays = (
            np.ascontiguousarray(x.detach().numpy(), dtype=np_dtype),
            np.ascontiguousarray(y.detach().numpy(), dtype=np_dtype),
            np.ascontiguousarray(t.detach().numpy(), dtype=np_dtype),
            np.ascontiguousarray(p.detach().numpy(), dtype=np_dtype),  # OFF where p <= 0
            np.ascontiguousarray(mask.numpy()),
            np.ascontiguousarray(u.detach().numpy()),
            np.asarray(references, np_dtype),
            np.array([1.0, 1e-9, -alpha, 1.0 / span], np_dtype),
        )
        images = np.empty((B, R, 2, 2, height + 2, width + 2), np_dtype)
        stats = np.empty((B, R, 3), np.float64)
        at = np.empty((B, R), np.float64)
        ec = np.empty((B, R), np.float64)
        kept = np.empty((B, R), np.float64)
        fwd, _ = _kernels.kernels(_kernels.use_threads())
        fwd(*arrays, int(height), int(width), images, stats, at, ec, kept)
        ctx.arrays, ctx.images, ctx.stats = arrays, images, stats
        ctx.geometry = (height, width, alpha)
        kept_t = torch.from_numpy(kept).to(dtype)
        n_nz = torch.from_numpy(stats[..., 0]).to(dtype)
        ctx.mark_non_differentiable(kept_t, n_nz)
        ctx.set_materialize_grads(False)
        return torch.from_numpy(at).to(dtype), torch.from_numpy(ec).to(dtype), kept_t, n_nz

    @staticmethod
    def backward(ctx, grad_at, grad_ec, _grad_kept, _grad_n_nz):
        height, width, alpha = ctx.geometry
        x, images, stats = ctx.arrays[0], ctx.images, ctx.stats
        B, N = x.shape
        R = stats.shape[1]
        g_at = np.zeros((B, R)) if grad_at is None else grad_at.detach().double().numpy()
        g_ec = np.zeros((B, R)) if grad_ec is None else grad_ec.detach().double().numpy()
        factors = np.empty((B, R, 3))  # k_at, k_ON, k_OFF (see the backward kernel)
        factors[..., 0] = 2.0 * g_at / (stats[..., 0] + 1e-9)
        factors[..., 1:] = (alpha * height * width) * g_ec[..., None] / (stats[..., 1:] * stats[..., 1:])
        grad_u = np.empty((B, R, N, 2), images.dtype)
        _, bwd = _kernels.kernels(_kernels.use_threads())
        bwd(*ctx.arrays, int(height), int(width), images, factors.astype(images.dtype), grad_u)
        grad = torch.from_numpy(grad_u).sum(dim=1)
        return grad, None, None, None, None, None, None


# The arguments of iwe.warped_event_images, plus the weights: the same warp, fused with the losses.
def event_image_terms(
    events: EventBatch,
    u: torch.Tensor,
    height: int,
    width: int,
    references: Sequence[float] = (0.0, 1.0),
    span: float = 1.0,
    alpha: float = 0.6,
    at_normalisation: AtNormalisation = "event_pixels",
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """L_AT(s_r), L_EC(s_r) and the kept splat weight for every batch element and reference.

    Arguments as ``iwe.warped_event_images``; alpha as ``event_count_loss``.
    at_normalisation: "event_pixels" (default) divides eq. 14's sum of squared average
    timestamps by N_nz + 1e-9, the number of pixels with C_+ + C_- > 0 (docs/method.md, "Losses");
    "sum" is eq. 14 as printed, the bare sum (N_nz is piecewise constant, so the gradient is the
    normalised one times N_nz).
    Returns (at, ec, kept), each (B, R) in u's dtype; at and ec are differentiable in u
    (fused backward), kept = sum over pixels of C_+ + C_- (not differentiable).
    """
    if at_normalisation not in AT_NORMALISATIONS:
        raise ValueError(f"at_normalisation must be one of {AT_NORMALISATIONS}, got {at_normalisation!r}")
    if _kernels is not None and use_cpu_kernels(u):
        fn = _EventImageTermsCompiled
    else:
        fn = _EventImageTerms
    at, ec, kept, n_nz = fn.apply(u, events, height, width, tuple(references), float(span), float(alpha))
    if at_normalisation == "sum":
        at = at * (n_nz + 1e-9)  # undo the division: eq. 14's bare sum
    return at, ec, kept
