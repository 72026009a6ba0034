"""Compiled CPU kernels (numba) for L_AT(s) and L_EC(s) straight from the events, and for the
other per-event and per-pixel loops of the losses (flow sampling, Charbonnier smoothness, the
forward warp of a flow field, input checks).

The same arithmetic as the torch path of ``image_terms.py`` (see its docstring for the
equations), but fused: one loop over the events splats the count and timestamp images of one
(batch element, reference time) pair, one pass over the pixels reduces them to L_AT, L_EC and
the kept weight, and the backward is one pass over the pixels that turns C and A into the
per-pixel factors of the gradient, then one loop over the events that reads them at each
event's 4 corners. The work is split into B x R independent tasks (each owns its images), so
there are no write races and B = 1 still uses two threads for the two reference times.

Arithmetic runs in the events' dtype (float32 for training, float64 for the checks): constants
come in as arrays of that dtype, since a Python float would promote every product to float64.
The pixel passes are written as branch-free row loops that LLVM turns into SIMD code; for that
the exp of L_EC is a polynomial in float32 (``_exp``), and row sums are added in float64.

Layout as in ``splat.py``: every image is padded by a 1-pixel ring (pixel (r, q) stored at
(r + 1, q + 1)); corners that fall outside the real image land on the ring and are ignored.

Used on CPU tensors (numba is a dependency; the callers decide per tensor); the torch paths are the
reference the tests compare against and the path for CUDA.

A forward kernel and its backward repeat the same set-up lines (shapes, constants in the
array's dtype): each is compiled as one self-contained loop nest.
"""

from __future__ import annotations

import functools
import math

import numba
import numpy as np
import torch
from numba import types
from numba.extending import overload

__all__ = ["kernels", "smoothness_kernels", "forward_warp_kernels", "warp_strips", "use_threads"]

_OPTIONS = dict(nogil=True, cache=True, fastmath=False, boundscheck=False, error_model="numpy")
# The image kernels may reassociate sums and contract multiply-adds, so that the pixel passes
# compile to SIMD loops (row sums are then added in float64); no flag that changes NaN/inf.
_VECTOR = dict(_OPTIONS, fastmath={"reassoc", "contract", "nsz"})

_LOG2E = np.float32(1.4426950408889634)
_LN2_HI = np.float32(0.693145751953125)  # ln 2 split in two so that n * ln 2 is exact
_LN2_LO = np.float32(1.428606765330187e-06)
_EXP_POLY = tuple(np.float32(c) for c in (  # minimax polynomial of (e^r - 1 - r) / r^2 on |r| <= ln2/2
    1.9875691500e-4, 1.3981999507e-3, 8.3334519073e-3, 4.1665795894e-2, 1.6666665459e-1, 5.0000001201e-1))


def _exp(v):  # pragma: no cover - replaced inside compiled code by the overload below
    return math.exp(v)


@overload(_exp, inline="always")
def _exp_overload(v):
    """exp for the compiled kernels: float64 -> math.exp; float32 -> a branch-free polynomial
    (relative error < 1e-7, arguments clamped to [-87, 88]) that LLVM can vectorize, which the
    libm call cannot be."""
    if isinstance(v, types.Float) and v.bitwidth == 32:
        c0, c1, c2, c3, c4, c5 = _EXP_POLY

        def impl(v):
            v = min(max(v, np.float32(-87.0)), np.float32(88.0))
            n = np.floor(v * _LOG2E + np.float32(0.5))
            r = v - n * _LN2_HI - n * _LN2_LO
            p = ((((c0 * r + c1) * r + c2) * r + c3) * r + c4) * r + c5
            p = p * r * r + r + np.float32(1.0)
            return p * np.int32((np.int32(n) + np.int32(127)) << np.int32(23)).view(np.float32)

        return impl
    return lambda v: math.exp(v)


@numba.njit(inline="always", **_OPTIONS)
def _warp_event(x, y, t, u, b, i, s, one, height, width):
    """Event i of window b warped to reference s (eq. 12) in the padded layout: (inside, row,
    col, fx, fy, dt), arithmetic in the arrays' dtype; ``inside`` False when all 4 corners fall
    outside the image (or on NaN)."""
    dt = s - t[b, i]
    xw = x[b, i] + dt * u[b, i, 0]
    yw = y[b, i] + dt * u[b, i, 1]
    x0f = np.floor(xw)
    y0f = np.floor(yw)
    inside = x0f >= -one and x0f <= width - 1 and y0f >= -one and y0f <= height - 1
    if not inside:
        return False, 0, 0, xw - xw, yw - yw, dt
    return True, int(y0f) + 1, int(x0f) + 1, xw - x0f, yw - y0f, dt


def _make(parallel: bool):
    loop = numba.prange if parallel else range

    @numba.njit(parallel=parallel, **_VECTOR)
    def forward(x, y, t, p, mask, u, refs, consts, height, width, images, stats, at, ec, kept):
        """p: (B, N) polarities (OFF where p <= 0). images: (B, R, 2 [ON, OFF], 2 [C, A], H + 2,
        W + 2) out: the count image C and the timestamp image A, kept for the backward.
        refs: (R,) and consts = [1, 1e-9, -alpha, 1 / span] in the events' dtype, which sets the
        arithmetic (float32 or float64). stats: (B, R, 3) out: N_nz, S_ON, S_OFF (for the
        backward). at, ec, kept: (B, R) out (float64)."""
        B, N = x.shape
        R = refs.shape[0]
        one, tiny, neg_alpha, inv_span = consts[0], consts[1], consts[2], consts[3]
        zero = one - one
        hw = height * width
        for task in loop(B * R):
            b = task // R
            r = task % R
            s = refs[r]
            img = images[b, r]
            img[:] = zero
            for i in range(N):
                if not mask[b, i]:
                    continue
                inside, row, col, fx, fy, dt = _warp_event(x, y, t, u, b, i, s, one, height, width)
                if not inside:
                    continue  # all 4 corners outside: dropped
                c = 1 if p[b, i] <= zero else 0  # OFF: p <= 0
                w = one - abs(dt) * inv_span
                gx = one - fx
                gy = one - fy
                count = img[c, 0]
                stamp = img[c, 1]
                k = gy * gx
                count[row, col] += k
                stamp[row, col] += k * w
                k = gy * fx
                count[row, col + 1] += k
                stamp[row, col + 1] += k * w
                k = fy * gx
                count[row + 1, col] += k
                stamp[row + 1, col] += k * w
                k = fy * fx
                count[row + 1, col + 1] += k
                stamp[row + 1, col + 1] += k * w
            sum_t2 = 0.0
            nnz = 0.0
            s_on = 0.0
            s_off = 0.0
            total = 0.0
            for rr in range(1, height + 1):  # one SIMD loop per row; ring pixels (dropped) skipped
                c_on, a_on = img[0, 0, rr], img[0, 1, rr]
                c_off, a_off = img[1, 0, rr], img[1, 1, rr]
                row_t2 = zero
                row_nz = zero
                row_on = zero
                row_off = zero
                row_total = zero
                for q in range(1, width + 1):
                    n_on = c_on[q]
                    n_off = c_off[q]
                    t_on = a_on[q] / (n_on + tiny)  # eq. 13 (0 where C = 0)
                    t_off = a_off[q] / (n_off + tiny)
                    x_on = _exp(neg_alpha * n_on)
                    x_off = _exp(neg_alpha * n_off)
                    row_t2 += t_on * t_on + t_off * t_off
                    row_nz += one if n_on + n_off > zero else zero
                    row_on += x_on
                    row_off += x_off
                    row_total += n_on + n_off
                sum_t2 += row_t2
                nnz += row_nz
                s_on += row_on
                s_off += row_off
                total += row_total
            at[b, r] = sum_t2 / (nnz + 1e-9)
            ec[b, r] = hw / s_on + hw / s_off - 2.0
            kept[b, r] = total
            stats[b, r, 0] = nnz
            stats[b, r, 1] = s_on
            stats[b, r, 2] = s_off

    @numba.njit(parallel=parallel, **_VECTOR)
    def backward(x, y, t, p, mask, u, refs, consts, height, width, images, factors, grad_u):
        """factors: (B, R, 3) [k_at, k_ON, k_OFF] in the events' dtype, with k_at = 2 dL/dL_AT /
        N_nz and k_P = alpha HW dL/dL_EC / S_P^2. Each task first fills a scratch
        (2, H + 2, W + 2, 2): per pixel [G0, G1] side by side (one cache line serves a corner
        pair), G = G0 + w G1 with G1 = k_at P1, G0 = k_P E - k_at P2 (P1 = T / (C + 1e-9), P2 = T P1:
        dL_AT/dA = k_at P1, dL_AT/dC = -k_at P2, dL_EC/dC = k_P E; eqs. 13-16), 0 on the ring
        (dropped corners). grad_u: (B, R, N, 2) out (summed over R by the caller)."""
        B, N = x.shape
        R = refs.shape[0]
        one, tiny, neg_alpha, inv_span = consts[0], consts[1], consts[2], consts[3]
        zero = one - one
        for task in loop(B * R):
            b = task // R
            r = task % R
            s = refs[r]
            img = images[b, r]
            gimg = np.empty((2, height + 2, width + 2, 2), images.dtype)
            k_at = factors[b, r, 0]
            for c in range(2):
                k_ec = factors[b, r, 1 + c]
                gimg[c, 0] = zero
                gimg[c, height + 1] = zero
                for rr in range(1, height + 1):
                    count, stamp = img[c, 0, rr], img[c, 1, rr]
                    g = gimg[c, rr]
                    g[0] = zero
                    g[width + 1] = zero
                    for q in range(1, width + 1):
                        inv = one / (count[q] + tiny)
                        p1 = stamp[q] * inv * inv
                        g[q, 0] = k_ec * _exp(neg_alpha * count[q]) - k_at * p1 * stamp[q] * inv
                        g[q, 1] = k_at * p1
            for i in range(N):
                grad_u[b, r, i, 0] = zero
                grad_u[b, r, i, 1] = zero
                if not mask[b, i]:
                    continue
                inside, row, col, fx, fy, dt = _warp_event(x, y, t, u, b, i, s, one, height, width)
                if not inside:
                    continue
                w = one - abs(dt) * inv_span
                g = gimg[1 if p[b, i] <= zero else 0]
                G00 = g[row, col, 0] + w * g[row, col, 1]
                G01 = g[row, col + 1, 0] + w * g[row, col + 1, 1]
                G10 = g[row + 1, col, 0] + w * g[row + 1, col, 1]
                G11 = g[row + 1, col + 1, 0] + w * g[row + 1, col + 1, 1]
                gx = (one - fy) * (G01 - G00) + fy * (G11 - G10)  # sum_c G_c dk_c/dx'
                gy = (one - fx) * (G10 - G00) + fx * (G11 - G01)  # sum_c G_c dk_c/dy'
                grad_u[b, r, i, 0] = gx * dt
                grad_u[b, r, i, 1] = gy * dt

    return forward, backward


def use_threads() -> bool:
    """Follow torch's intra-op thread count: several threads -> the parallel kernels with as
    many numba threads; one thread (e.g. inside a forked env worker, where a threading runtime
    inherited from the parent is not safe to start) -> the serial kernels."""
    threads = min(torch.get_num_threads(), numba.config.NUMBA_NUM_THREADS)
    if threads <= 1:
        return False
    numba.set_num_threads(threads)
    return True


@functools.cache
def kernels(parallel: bool):
    """(forward, backward) compiled for threads (``parallel``) or for one thread."""
    return _make(parallel)


# The 4 directions (d_row, d_col) of smoothness._DIRECTIONS: right (0, 1), down (1, 0),
# down-right (1, 1), up-right (-1, 1). Each kernel calls an inlined per-direction helper once per
# direction with literal offsets: with run-time offsets LLVM does not vectorize the row loops
# (about 10x slower).


@numba.njit(inline="always", **_VECTOR)
def _charbonnier_direction(img, has, scale, eps2, zero, dr, dc):
    """Sum of sqrt(d^2 + eps^2) over counted pairs (r, q) -> (r + dr, q + dc) of one image."""
    H, W = img.shape
    acc = 0.0
    for r in range(max(0, -dr), H - max(0, dr)):
        a, b = img[r], img[r + dr]
        ma, mb = has[r], has[r + dr]
        row = zero
        for q in range(W - dc):
            d = (b[q + dc] - a[q]) * scale
            row += math.sqrt(d * d + eps2) if ma[q] and mb[q + dc] else zero
        acc += row
    return acc


@numba.njit(inline="always", **_VECTOR)
def _charbonnier_direction_grad(img, has, scale, out, g_b, eps2, zero, slope, dr, dc):
    """Adds g_b d rho / d d of one direction's pairs to out (g_b includes the 1 / flow_scaling
    of d's derivative); slope: (W,) scratch."""
    H, W = img.shape
    for r in range(max(0, -dr), H - max(0, dr)):
        a, b = img[r], img[r + dr]
        ma, mb = has[r], has[r + dr]
        for q in range(W - dc):
            d = (b[q + dc] - a[q]) * scale
            slope[q] = g_b * d / math.sqrt(d * d + eps2) if ma[q] and mb[q + dc] else zero
        for q in range(W - dc):
            out[r + dr, q + dc] += slope[q]
        for q in range(W - dc):
            out[r, q] -= slope[q]


def _make_smoothness(parallel: bool):
    loop = numba.prange if parallel else range

    # forward and backward open alike (the same constants and per-task views): each kernel
    # unpacks its own, so that it reads alone.
    @numba.njit(parallel=parallel, **_VECTOR)
    def forward(f, event_mask, consts, total):
        """f: (B, 2, H, W) flow in pixels; event_mask: (B, H, W) bool; consts = [eps,
        1 / flow_scaling] in f's dtype; total: (B, 2) out, per component: the sum over counted
        pairs of sqrt(d^2 + eps^2), d the difference in network units (pixels / flow_scaling).
        One task per (batch element, component); one SIMD loop per row and direction
        (uncounted pairs select 0)."""
        B = f.shape[0]
        eps2 = consts[0] * consts[0]
        zero = consts[0] - consts[0]
        scale = consts[1]
        for task in loop(2 * B):
            b = task // 2
            img = f[b, task % 2]
            has = event_mask[b]
            total[b, task % 2] = (_charbonnier_direction(img, has, scale, eps2, zero, 0, 1)
                                  + _charbonnier_direction(img, has, scale, eps2, zero, 1, 0)
                                  + _charbonnier_direction(img, has, scale, eps2, zero, 1, 1)
                                  + _charbonnier_direction(img, has, scale, eps2, zero, -1, 1))

    @numba.njit(parallel=parallel, **_VECTOR)
    def backward(f, event_mask, consts, grad_total, grad):
        """grad_total: (B,) in f's dtype; grad: (B, 2, H, W) out, d total[b] / d f times
        grad_total[b] (d rho / d d = d / rho, times 1 / flow_scaling)."""
        B, _, _, W = f.shape
        eps2 = consts[0] * consts[0]
        zero = consts[0] - consts[0]
        scale = consts[1]
        for task in loop(2 * B):
            b = task // 2
            img = f[b, task % 2]
            has = event_mask[b]
            out = grad[b, task % 2]
            out[:] = zero
            g_b = grad_total[b] * scale
            slope = np.empty(W, f.dtype)
            _charbonnier_direction_grad(img, has, scale, out, g_b, eps2, zero, slope, 0, 1)
            _charbonnier_direction_grad(img, has, scale, out, g_b, eps2, zero, slope, 1, 0)
            _charbonnier_direction_grad(img, has, scale, out, g_b, eps2, zero, slope, 1, 1)
            _charbonnier_direction_grad(img, has, scale, out, g_b, eps2, zero, slope, -1, 1)

    return forward, backward


@functools.cache
def smoothness_kernels(parallel: bool):
    """(forward, backward) of the Charbonnier sum, for threads or for one thread."""
    return _make_smoothness(parallel)


def _make_event_mask(parallel: bool):
    loop = numba.prange if parallel else range

    @numba.njit(parallel=parallel, **_OPTIONS)
    def event_mask(x, y, mask, out):
        """out (B, H, W) bool, all False on entry: set True at pixels holding a valid event,
        coordinates rounded half to even. Each batch element in two halves of its events (so
        B = 1 uses two threads); both halves only ever store True, so they may share a pixel."""
        B, H, W = out.shape
        N = x.shape[1]
        for task in loop(2 * B):
            b = task // 2
            for i in range((task % 2) * N // 2, (task % 2 + 1) * N // 2):
                if not mask[b, i]:
                    continue
                xi = np.round(x[b, i])
                yi = np.round(y[b, i])
                if xi >= 0 and xi < W and yi >= 0 and yi < H:
                    out[b, int(yi), int(xi)] = True

    return event_mask


@functools.cache
def event_mask_kernel(parallel: bool):
    """The event-pixel mask of ``smoothness.event_pixel_mask``, for threads or for one thread."""
    return _make_event_mask(parallel)


@numba.njit(inline="always", **_OPTIONS)
def _splat_taps(x, y):
    """Top-left corner and fractions of a bilinear splat at (x, y), not clamped: (x0, y0, fx, fy)."""
    x0f = math.floor(x)
    y0f = math.floor(y)
    return int(x0f), int(y0f), x - x0f, y - y0f


#: Images of a batch smaller than this are splatted in this many row strips at once (each
#: into its own accumulator, summed afterwards), so that a single window also uses several
#: threads. Fixed by the batch size, not the thread count: results do not depend on threads.
WARP_STRIPS = 4


def warp_strips(batch: int) -> int:
    """Row strips per image for the forward warp of a batch of ``batch`` flows."""
    return max(1, WARP_STRIPS // max(1, batch))


def _make_forward_warp(parallel: bool):
    loop = numba.prange if parallel else range

    @numba.njit(parallel=parallel, **_OPTIONS)
    def splat(flow, partial):
        """Eq. 9's splatting of flow (B, 2, H, W) into partial (B, S, H, W, 3): strip s of image
        b (rows s H / S .. (s + 1) H / S) splats [weight, weight u_x, weight u_y] at the four
        bilinear corners of each pixel's displaced position into partial[b, s] (out-of-image
        corners dropped). One task per (image, strip)."""
        B, _, H, W = flow.shape
        S = partial.shape[1]
        for task in loop(B * S):
            b = task // S
            s = task - b * S
            acc = partial[b, s]
            acc[:] = 0.0
            for r in range(s * H // S, (s + 1) * H // S):
                for q in range(W):
                    ux = flow[b, 0, r, q]
                    uy = flow[b, 1, r, q]
                    x0, y0, fx, fy = _splat_taps(q + ux, r + uy)
                    if 0 <= x0 and x0 + 1 < W and 0 <= y0 and y0 + 1 < H:
                        # all four corners inside (most pixels): no per-corner tests
                        for k in range(4):
                            cx = x0 + (k & 1)
                            cy = y0 + (k >> 1)
                            w = (fx if k & 1 else 1.0 - fx) * (fy if k >> 1 else 1.0 - fy)
                            acc[cy, cx, 0] += w
                            acc[cy, cx, 1] += w * ux
                            acc[cy, cx, 2] += w * uy
                        continue
                    for k in range(4):
                        cx = x0 + (k & 1)
                        cy = y0 + (k >> 1)
                        if cx < 0 or cx >= W or cy < 0 or cy >= H:
                            continue
                        w = (fx if k & 1 else 1.0 - fx) * (fy if k >> 1 else 1.0 - fy)
                        acc[cy, cx, 0] += w
                        acc[cy, cx, 1] += w * ux
                        acc[cy, cx, 2] += w * uy

    @numba.njit(parallel=parallel, **_OPTIONS)
    def normalize(partial, acc, out, min_weight):
        """acc (B, H, W, 3) out: the strips of partial summed; out (B, 2, H, W) out: the splatted
        flow over the splatted weight, 0 (a hole) where the weight is not above ``min_weight``
        (>= 0). One task per image row."""
        B, S, H, W, _ = partial.shape
        for task in loop(B * H):
            b = task // H
            r = task - b * H
            for q in range(W):
                a0 = partial[b, 0, r, q, 0]
                a1 = partial[b, 0, r, q, 1]
                a2 = partial[b, 0, r, q, 2]
                for s in range(1, S):
                    a0 += partial[b, s, r, q, 0]
                    a1 += partial[b, s, r, q, 1]
                    a2 += partial[b, s, r, q, 2]
                acc[b, r, q, 0] = a0
                acc[b, r, q, 1] = a1
                acc[b, r, q, 2] = a2
                if a0 > min_weight:
                    out[b, 0, r, q] = a1 / a0
                    out[b, 1, r, q] = a2 / a0
                else:
                    out[b, 0, r, q] = 0.0
                    out[b, 1, r, q] = 0.0

    @numba.njit(parallel=parallel, **_OPTIONS)
    def target_gradients(acc, out, grad_out, target, min_weight):
        """target (B, H, W, 3) out: per target pixel with weight A0 > min_weight,
        d/dA0 = -(g . out) / A0 and d/dA_c = g_c / A0 (0 at holes), from acc (B, H, W, 3), out
        and grad_out (B, 2, H, W). One task per image row."""
        B, H, W, _ = acc.shape
        for task in loop(B * H):
            b = task // H
            r = task - b * H
            for q in range(W):
                a = acc[b, r, q, 0]
                if a > min_weight:
                    g0 = grad_out[b, 0, r, q]
                    g1 = grad_out[b, 1, r, q]
                    target[b, r, q, 0] = -(g0 * out[b, 0, r, q] + g1 * out[b, 1, r, q]) / a
                    target[b, r, q, 1] = g0 / a
                    target[b, r, q, 2] = g1 / a
                else:
                    target[b, r, q, 0] = 0.0
                    target[b, r, q, 1] = 0.0
                    target[b, r, q, 2] = 0.0

    @numba.njit(parallel=parallel, **_OPTIONS)
    def gather(flow, target, grad_flow):
        """grad_flow (B, 2, H, W) out: the gradient of sum(grad_out * forward(flow)), each source
        pixel reading :func:`target_gradients` at its 4 corners: through the bilinear weights
        (x, y move with the flow) and through the splatted values. One task per image row."""
        B, _, H, W = flow.shape
        for task in loop(B * H):
            b = task // H
            r = task - b * H
            for q in range(W):
                ux = flow[b, 0, r, q]
                uy = flow[b, 1, r, q]
                x0, y0, fx, fy = _splat_taps(q + ux, r + uy)
                gx = 0.0
                gy = 0.0
                for k in range(4):
                    cx = x0 + (k & 1)
                    cy = y0 + (k >> 1)
                    if cx < 0 or cx >= W or cy < 0 or cy >= H:
                        continue
                    wx = fx if k & 1 else 1.0 - fx
                    wy = fy if k >> 1 else 1.0 - fy
                    dwx = 1.0 if k & 1 else -1.0  # d wx / dx
                    dwy = 1.0 if k >> 1 else -1.0  # d wy / dy
                    g_a = target[b, cy, cx, 0]
                    g_x = target[b, cy, cx, 1]
                    g_y = target[b, cy, cx, 2]
                    through_weight = g_a + ux * g_x + uy * g_y
                    gx += dwx * wy * through_weight + wx * wy * g_x
                    gy += wx * dwy * through_weight + wx * wy * g_y
                grad_flow[b, 0, r, q] = gx
                grad_flow[b, 1, r, q] = gy

    return splat, normalize, target_gradients, gather


@functools.cache
def forward_warp_kernels(parallel: bool):
    """(splat, normalize, target_gradients, gather) of the prior-flow forward warp (eq. 9), for
    threads or one thread: the forward is splat then normalize, the backward target_gradients
    then gather."""
    return _make_forward_warp(parallel)
