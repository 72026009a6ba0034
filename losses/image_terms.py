"""L_AT(s) and L_EC(s) straight from the events, with a fused analytic backward.

Same values as ``average_timestamp_loss(*warped_event_images(...))`` and
``event_count_loss(count)`` (the forward calls exactly those on the same images), but the
backward does not go through autograd's temporaries: per pixel it forms dL/dC_P and dL/dA_P
(eqs. 13-16), gathers them at each event's 4 corners (one gather, the adjoint of the one
scatter_add of the forward), and uses the separable kernel's derivative

    dL/dx' = sum_c G_c dk_c/dx',   G_c = dL/dC(q_c) + w_i dL/dA(q_c),

with dk/dx' = +-wy (right/left corners) and dk/dy' = +-wx (lower/upper corners). Then
dL/du_i = sum_s (s - t_i) dL/dx'_i(s) (eq. 12). This is the exact gradient of the same
piecewise-smooth function autograd would differentiate (N_nz is piecewise constant); the tests
check it with torch.autograd.gradcheck in float64.
"""

from __future__ import annotations

from typing import Sequence

import torch

from .average_timestamp import average_timestamp_loss
from .event_count import event_count_loss
from .iwe import splat_counts_and_stamps, warped_corners
from .splat import crop_padding

__all__ = ["event_image_terms"]


class _EventImageTerms(torch.autograd.Function):
    @staticmethod
    def forward(ctx, u, x, y, t, p, mask, height, width, references, span, alpha):
        index, wx, wy, inside, closeness, dt = warped_corners(
            x, y, t, p, mask, u, height, width, references, span
        )
        padded = splat_counts_and_stamps(index, wx, wy, closeness, height, width)
        images = crop_padding(padded)  # (B, R, 2 [count, stamp], 2 [ON, OFF], H, W)
        count, stamp = images[:, :, 0], images[:, :, 1]
        at = average_timestamp_loss(count, stamp)  # (B, R), eqs. 13-14
        ec = event_count_loss(count, alpha)  # (B, R), eqs. 15-16
        kept = count.sum(dim=(2, 3, 4))  # (B, R) splat weight inside the image
        ctx.save_for_backward(index, wx, wy, inside, closeness, dt, padded)
        ctx.geometry = (height, width, alpha)
        ctx.mark_non_differentiable(kept)
        ctx.set_materialize_grads(False)  # None for an unused output (e.g. ec in at_loss)
        return at, ec, kept

    @staticmethod
    def backward(ctx, grad_at, grad_ec, _grad_kept):
        index, wx, wy, inside, closeness, dt, padded = ctx.saved_tensors
        height, width, alpha = ctx.geometry
        B, R, N = closeness.shape
        images = crop_padding(padded)
        count, stamp = images[:, :, 0], images[:, :, 1]  # (B, R, 2, H, W)
        grads = torch.zeros_like(padded)  # ring stays 0: dropped corners get no gradient
        g_count, g_stamp = crop_padding(grads[:, :, 0]), crop_padding(grads[:, :, 1])
        if grad_at is not None:  # L_AT = sum T^2 / Z, T = A / (C + 1e-9)
            inv = 1.0 / (count + 1e-9)
            T = stamp * inv
            n_nz = (count.sum(dim=2) > 0).sum(dim=(-2, -1)).to(count.dtype)  # (B, R)
            coef = (2 * grad_at / (n_nz + 1e-9)).view(B, R, 1, 1, 1)
            g_stamp.copy_(T * inv * coef)  # dL_AT/dA = 2 T / (C + 1e-9) / Z
            g_count.copy_(-g_stamp * T)  # dL_AT/dC = -2 T^2 / (C + 1e-9) / Z
        if grad_ec is not None:  # L_EC = sum_P HW / S_P - 2, S_P = sum exp(-alpha C_P)
            E = torch.exp(-alpha * count)
            S = E.sum(dim=(-2, -1), keepdim=True)  # (B, R, 2, 1, 1)
            scale = (alpha * height * width) * grad_ec.view(B, R, 1, 1, 1) / (S * S)
            g_count.add_(E * scale)
        rows = B * R
        idx = index.reshape(rows, 1, 4 * N).expand(rows, 2, 4 * N)
        gathered = grads.view(rows, 2, -1).gather(2, idx).view(B, R, 2, 2, 2, N)
        # G_c = dL/dC + w dL/dA at each corner, as (B, R, 2 [row a], 2 [col b], N)
        G = torch.addcmul(gathered[:, :, 0], gathered[:, :, 1], closeness.view(B, R, 1, 1, N))
        gx = ((G[:, :, :, 1] - G[:, :, :, 0]) * wy).sum(dim=2)  # dL/dx' (wy holds the inside mask)
        gy = ((G[:, :, 1] - G[:, :, 0]) * wx).sum(dim=2) * inside  # dL/dy'
        grad_u = torch.stack([(gx * dt).sum(dim=1), (gy * dt).sum(dim=1)], dim=-1)  # eq. 12
        return grad_u, None, None, None, None, None, None, None, None, None, None


def event_image_terms(
    x: torch.Tensor,
    y: torch.Tensor,
    t: torch.Tensor,
    p: torch.Tensor,
    mask: torch.Tensor,
    u: torch.Tensor,
    height: int,
    width: int,
    references: Sequence[float] = (0.0, 1.0),
    span: float = 1.0,
    alpha: float = 0.6,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """L_AT(s_r), L_EC(s_r) and the kept splat weight for every batch element and reference.

    Arguments as ``iwe.warped_event_images``; alpha as ``event_count_loss``.
    Returns (at, ec, kept), each (B, R) in u's dtype; at and ec are differentiable in u
    (fused backward), kept = sum over pixels of C_+ + C_- (not differentiable).
    """
    return _EventImageTerms.apply(u, x, y, t, p, mask, height, width, tuple(references),
                                  float(span), float(alpha))
