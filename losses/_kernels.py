"""Compiled CPU kernels (numba) for L_AT(s) and L_EC(s) straight from the events.

The same arithmetic as the torch path of ``image_terms.py`` (see its docstring for the
equations), but fused: one loop over the events splats the count and timestamp images of one
(batch element, reference time) pair, one loop over the pixels reduces them to L_AT, L_EC and
the kept weight, and the backward is one more loop over the events that reads the images at
each event's 4 corners. The work is split into B x R independent tasks (each owns its images),
so there are no write races and B = 1 still uses two threads for the two reference times.

Layout as in ``splat.py``: every image is padded by a 1-pixel ring (pixel (r, q) stored at
(r + 1, q + 1)); corners that fall outside the real image land on the ring and are ignored.

Used on CPU tensors when numba is importable (``image_terms.py`` decides); the torch path is
the reference the tests compare against and the path for CUDA.
"""

from __future__ import annotations

import functools
import math

import numba
import numpy as np
import torch

__all__ = ["kernels", "smoothness_kernels", "use_threads"]

_OPTIONS = dict(nogil=True, cache=True, fastmath=False, boundscheck=False, error_model="numpy")


@numba.njit(inline="always", **_OPTIONS)
def _corner_gradient(img, c, rr, q, height, width, w, k_at, k_ec):
    """G = dL/dC + w dL/dA at padded pixel (rr, q) of polarity c; 0 on the ring (dropped).
    With k_at = 2 dL/dL_AT / Z: dL_AT/dA = k_at T / (C + 1e-9) = k_at P1 and dL_AT/dC = -T dL_AT/dA
    = -k_at P2; dL_EC/dC = k_ec E with k_ec = alpha HW dL/dL_EC / S^2 (eqs. 13-16)."""
    if rr == 0 or rr == height + 1 or q == 0 or q == width + 1:
        return 0.0
    return k_at * (w * img[1, c, rr, q] - img[0, c, rr, q]) + k_ec * img[2, c, rr, q]


@numba.njit(inline="always", **_OPTIONS)
def _warp_event(x, y, t, u, b, i, s, height, width):
    """Event i of window b warped to reference s (eq. 12) in the padded layout: (inside, row,
    col, fx, fy, dt); ``inside`` False when all 4 corners fall outside the image (or on NaN)."""
    dt = s - t[b, i]
    xw = x[b, i] + dt * u[b, i, 0]
    yw = y[b, i] + dt * u[b, i, 1]
    x0f = math.floor(xw)
    y0f = math.floor(yw)
    inside = x0f >= -1.0 and x0f <= width - 1.0 and y0f >= -1.0 and y0f <= height - 1.0
    if not inside:
        return False, 0, 0, 0.0, 0.0, dt
    return True, int(y0f) + 1, int(x0f) + 1, xw - x0f, yw - y0f, dt


@numba.njit(inline="always", **_OPTIONS)
def _finish_pixel(img, c, rr, q, neg_alpha):
    """One polarity of one pixel after splatting: returns (T^2, E) with T = A / (C + 1e-9)
    (eq. 13) and E = exp(-alpha C), and keeps the backward factors in place of C and A:
    P1 = T / (C + 1e-9), P2 = T P1 (0 where C = 0), E."""
    count = img[0, c, rr, q]
    if count == 0:
        img[2, c, rr, q] = 1.0
        return 0.0, 1.0
    inv = 1.0 / (count + 1e-9)
    tt = img[1, c, rr, q] * inv
    e = math.exp(neg_alpha[0] * count)
    img[1, c, rr, q] = tt * inv
    img[0, c, rr, q] = tt * tt * inv
    img[2, c, rr, q] = e
    return tt * tt, e


def _make(parallel: bool):
    loop = numba.prange if parallel else range

    @numba.njit(parallel=parallel, **_OPTIONS)
    def forward(x, y, t, off, mask, u, refs, span, neg_alpha, height, width, images, stats, at, ec, kept):
        """images: (B, R, 3, 2, H + 2, W + 2) out, [P2, P1, E] x [ON, OFF] per pixel, for the
        backward (the count and timestamp images are built in the first two slots, then
        replaced): P1 = T / (C + 1e-9), P2 = T P1, E = exp(-alpha C); P1 = P2 = 0 where C = 0.
        neg_alpha: (1,) array of -alpha in the images' dtype (float32 images: float32 exp).
        stats: (B, R, 3) out: N_nz, S_ON, S_OFF (for the backward). at, ec, kept: (B, R) out."""
        B, N = x.shape
        R = refs.shape[0]
        hp, wp = height + 2, width + 2
        hw = height * width
        for task in loop(B * R):
            b = task // R
            r = task % R
            s = refs[r]
            img = images[b, r]
            img[0] = 0.0
            img[1] = 0.0
            for i in range(N):
                if not mask[b, i]:
                    continue
                inside, row, col, fx, fy, dt = _warp_event(x, y, t, u, b, i, s, height, width)
                if not inside:
                    continue  # all 4 corners outside: dropped
                c = 1 if off[b, i] else 0
                w = 1.0 - abs(dt) / span
                k00 = (1.0 - fy) * (1.0 - fx)
                k01 = (1.0 - fy) * fx
                k10 = fy * (1.0 - fx)
                k11 = fy * fx
                img[0, c, row, col] += k00
                img[1, c, row, col] += k00 * w
                img[0, c, row, col + 1] += k01
                img[1, c, row, col + 1] += k01 * w
                img[0, c, row + 1, col] += k10
                img[1, c, row + 1, col] += k10 * w
                img[0, c, row + 1, col + 1] += k11
                img[1, c, row + 1, col + 1] += k11 * w
            sum_t2 = 0.0
            nnz = 0
            s_on = 0.0
            s_off = 0.0
            total = 0.0
            for rr in range(1, hp - 1):
                for q in range(1, wp - 1):
                    c_on = img[0, 0, rr, q]
                    c_off = img[0, 1, rr, q]
                    if c_on + c_off > 0:
                        nnz += 1
                    total += c_on + c_off
                    t2_on, e_on = _finish_pixel(img, 0, rr, q, neg_alpha)
                    t2_off, e_off = _finish_pixel(img, 1, rr, q, neg_alpha)
                    sum_t2 += t2_on + t2_off
                    s_on += e_on
                    s_off += e_off
            at[b, r] = sum_t2 / (nnz + 1e-9)
            ec[b, r] = hw / s_on + hw / s_off - 2.0
            kept[b, r] = total
            stats[b, r, 0] = nnz
            stats[b, r, 1] = s_on
            stats[b, r, 2] = s_off

    @numba.njit(parallel=parallel, **_OPTIONS)
    def backward(x, y, t, off, mask, u, refs, span, alpha, height, width, images, stats, grad_at, grad_ec, grad_u):
        """grad_at, grad_ec: (B, R). grad_u: (B, R, N, 2) out (summed over R by the caller)."""
        B, N = x.shape
        R = refs.shape[0]
        hw = height * width
        for task in loop(B * R):
            b = task // R
            r = task % R
            s = refs[r]
            img = images[b, r]
            nnz = stats[b, r, 0]
            s_on = stats[b, r, 1]
            s_off = stats[b, r, 2]
            k_at = 2.0 * grad_at[b, r] / (nnz + 1e-9)
            k_on = alpha * hw * grad_ec[b, r] / (s_on * s_on)
            k_off = alpha * hw * grad_ec[b, r] / (s_off * s_off)
            for i in range(N):
                grad_u[b, r, i, 0] = 0.0
                grad_u[b, r, i, 1] = 0.0
                if not mask[b, i]:
                    continue
                inside, row, col, fx, fy, dt = _warp_event(x, y, t, u, b, i, s, height, width)
                if not inside:
                    continue
                c = 1 if off[b, i] else 0
                k_ec = k_off if c == 1 else k_on
                w = 1.0 - abs(dt) / span
                g0 = _corner_gradient(img, c, row, col, height, width, w, k_at, k_ec)
                g1 = _corner_gradient(img, c, row, col + 1, height, width, w, k_at, k_ec)
                g2 = _corner_gradient(img, c, row + 1, col, height, width, w, k_at, k_ec)
                g3 = _corner_gradient(img, c, row + 1, col + 1, height, width, w, k_at, k_ec)
                gx = (1.0 - fy) * (g1 - g0) + fy * (g3 - g2)  # sum_c G_c dk_c/dx'
                gy = (1.0 - fx) * (g2 - g0) + fx * (g3 - g1)  # sum_c G_c dk_c/dy'

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


_DIRECTIONS = np.array([[0, 1], [1, 0], [1, 1], [-1, 1]], np.int64)  # as smoothness._DIRECTIONS


@numba.njit(inline="always", **_OPTIONS)
def _pair(event_mask, b, r, c, k):
    """Neighbour k of pixel (r, c) of window b: (counted, r2, c2); counted when it lies in the
    image and holds an event (the caller has checked (r, c) itself)."""
    r2 = r + _DIRECTIONS[k, 0]
    c2 = c + _DIRECTIONS[k, 1]
    H, W = event_mask.shape[1], event_mask.shape[2]
    return not (r2 < 0 or r2 >= H or c2 >= W or not event_mask[b, r2, c2]), r2, c2


def _make_smoothness(parallel: bool):
    loop = numba.prange if parallel else range

    @numba.njit(parallel=parallel, **_OPTIONS)
    def forward(f, event_mask, eps, total):
        """f: (B, 2, H, W) flow in network units; event_mask: (B, H, W) bool; total: (B,) out,
        sum over counted pairs and components of sqrt(d^2 + eps^2)."""
        B, _, H, W = f.shape
        for b in loop(B):
            acc = 0.0
            for r in range(H):
                for c in range(W):
                    if not event_mask[b, r, c]:
                        continue
                    for k in range(4):
                        counted, r2, c2 = _pair(event_mask, b, r, c, k)
                        if not counted:
                            continue
                        for ch in range(2):
                            d = f[b, ch, r2, c2] - f[b, ch, r, c]
                            acc += math.sqrt(d * d + eps * eps)
            total[b] = acc

    @numba.njit(parallel=parallel, **_OPTIONS)
    def backward(f, event_mask, eps, grad_total, grad):
        """grad: (B, 2, H, W) out, d total[b] / d f times grad_total[b]."""
        B, _, H, W = f.shape
        for b in loop(B):
            g_b = grad_total[b]
            grad[b] = 0.0
            for r in range(H):
                for c in range(W):
                    if not event_mask[b, r, c]:
                        continue
                    for k in range(4):
                        counted, r2, c2 = _pair(event_mask, b, r, c, k)
                        if not counted:
                            continue
                        for ch in range(2):
                            d = f[b, ch, r2, c2] - f[b, ch, r, c]
                            g = g_b * d / math.sqrt(d * d + eps * eps)
                            grad[b, ch, r2, c2] += g
                            grad[b, ch, r, c] -= g

    return forward, backward


@functools.cache
def smoothness_kernels(parallel: bool):
    """(forward, backward) of the Charbonnier sum, for threads or for one thread."""
    return _make_smoothness(parallel)


@numba.njit(inline="always", **_OPTIONS)
def _bilinear_taps(x, y, H, W):
    """Corner columns/rows and fractions of a bilinear sample at (x, y), clamped to the image
    ("border"): (x0, x1, y0, y1, fx, fy)."""
    xi = min(max(x, 0.0), W - 1.0)
    yi = min(max(y, 0.0), H - 1.0)
    x0 = int(math.floor(xi))
    y0 = int(math.floor(yi))
    return x0, min(x0 + 1, W - 1), y0, min(y0 + 1, H - 1), xi - x0, yi - y0


def _make_sampling(parallel: bool):
    loop = numba.prange if parallel else range

    @numba.njit(parallel=parallel, **_OPTIONS)
    def forward(flow, x, y, mask, out):
        """Bilinear sample of flow (B, 2, H, W) at (x, y) (B, N), coordinates clamped to the
        image ("border"); out: (B, N, 2); 0 where mask (B, N) is False (padding)."""
        B, _, H, W = flow.shape
        N = x.shape[1]
        for b in loop(B):
            for i in range(N):
                if not mask[b, i]:
                    out[b, i, 0] = 0.0
                    out[b, i, 1] = 0.0
                    continue
                x0, x1, y0, y1, fx, fy = _bilinear_taps(x[b, i], y[b, i], H, W)
                for c in range(2):
                    out[b, i, c] = ((1.0 - fy) * ((1.0 - fx) * flow[b, c, y0, x0] + fx * flow[b, c, y0, x1])
                                    + fy * ((1.0 - fx) * flow[b, c, y1, x0] + fx * flow[b, c, y1, x1]))

    @numba.njit(parallel=parallel, **_OPTIONS)
    def backward(grad_out, x, y, mask, grad_flow):
        """grad_flow (B, 2, H, W) out: the adjoint of ``forward``."""
        B, _, H, W = grad_flow.shape
        N = x.shape[1]
        for b in loop(B):
            grad_flow[b] = 0.0
            for i in range(N):
                if not mask[b, i]:
                    continue
                x0, x1, y0, y1, fx, fy = _bilinear_taps(x[b, i], y[b, i], H, W)
                for c in range(2):
                    g = grad_out[b, i, c]
                    grad_flow[b, c, y0, x0] += (1.0 - fy) * (1.0 - fx) * g
                    grad_flow[b, c, y0, x1] += (1.0 - fy) * fx * g
                    grad_flow[b, c, y1, x0] += fy * (1.0 - fx) * g
                    grad_flow[b, c, y1, x1] += fy * fx * g

    @numba.njit(parallel=parallel, **_OPTIONS)
    def event_mask(x, y, mask, out):
        """out (B, H, W) bool: pixels holding a valid event, coordinates rounded half to even."""
        B, H, W = out.shape
        N = x.shape[1]
        for b in loop(B):
            out[b] = False
            for i in range(N):
                if not mask[b, i]:
                    continue
                xi = np.round(x[b, i])
                yi = np.round(y[b, i])
                if xi >= 0 and xi < W and yi >= 0 and yi < H:
                    out[b, int(yi), int(xi)] = True

    return forward, backward, event_mask


@functools.cache
def sampling_kernels(parallel: bool):
    """(sample forward, sample backward, event-pixel mask), for threads or for one thread."""
    return _make_sampling(parallel)


@numba.njit(inline="always", **_OPTIONS)
def _splat_taps(x, y):
    """Top-left corner and fractions of a bilinear splat at (x, y), not clamped: (x0, y0, fx, fy)."""
    x0f = math.floor(x)
    y0f = math.floor(y)
    return int(x0f), int(y0f), x - x0f, y - y0f


def _make_forward_warp(parallel: bool):
    loop = numba.prange if parallel else range

    @numba.njit(parallel=parallel, **_OPTIONS)
    def forward(flow, acc, out):
        """Eq. 9 for flow (B, 2, H, W): acc (B, 3, H, W) out = the splatted weight and the two
        splatted flow components (out-of-image corners dropped); out (B, 2, H, W) = their
        ratio, 0 where no weight arrived. One task per batch element (each owns its images)."""
        B, _, H, W = flow.shape
        for b in loop(B):
            acc[b] = 0.0
            for r in range(H):
                for q in range(W):
                    ux = flow[b, 0, r, q]
                    uy = flow[b, 1, r, q]
                    x0, y0, fx, fy = _splat_taps(q + ux, r + uy)
                    for k in range(4):
                        cx = x0 + (k & 1)
                        cy = y0 + (k >> 1)
                        if cx < 0 or cx >= W or cy < 0 or cy >= H:
                            continue
                        w = (fx if k & 1 else 1.0 - fx) * (fy if k >> 1 else 1.0 - fy)
                        acc[b, 0, cy, cx] += w
                        acc[b, 1, cy, cx] += w * ux
                        acc[b, 2, cy, cx] += w * uy
            for r in range(H):
                for q in range(W):
                    a = acc[b, 0, r, q]
                    if a > 0:
                        out[b, 0, r, q] = acc[b, 1, r, q] / a
                        out[b, 1, r, q] = acc[b, 2, r, q] / a
                    else:
                        out[b, 0, r, q] = 0.0
                        out[b, 1, r, q] = 0.0

    @numba.njit(parallel=parallel, **_OPTIONS)
    def backward(flow, acc, out, grad_out, grad_flow):
        """grad_flow (B, 2, H, W) out: the gradient of sum(grad_out * forward(flow)).

        Per target pixel with weight A0 > 0: d/dA0 = -(g . out) / A0, d/dA_c = g_c / A0 (kept in
        acc, which the forward no longer needs); each source pixel then reads them at its 4
        corners: through the bilinear weights (x, y move with the flow) and through the values."""
        B, _, H, W = flow.shape
        for b in loop(B):
            for r in range(H):
                for q in range(W):
                    a = acc[b, 0, r, q]
                    if a > 0:
                        g0 = grad_out[b, 0, r, q]
                        g1 = grad_out[b, 1, r, q]
                        acc[b, 0, r, q] = -(g0 * out[b, 0, r, q] + g1 * out[b, 1, r, q]) / a
                        acc[b, 1, r, q] = g0 / a
                        acc[b, 2, r, q] = g1 / a
                    else:
                        acc[b, 0, r, q] = 0.0
                        acc[b, 1, r, q] = 0.0
                        acc[b, 2, r, q] = 0.0
            for r in range(H):
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
                        g_a = acc[b, 0, cy, cx]
                        g_x = acc[b, 1, cy, cx]
                        g_y = acc[b, 2, cy, cx]
                        through_weight = g_a + ux * g_x + uy * g_y
                        gx += dwx * wy * through_weight + wx * wy * g_x
                        gy += wx * dwy * through_weight + wx * wy * g_y
                    grad_flow[b, 0, r, q] = gx
                    grad_flow[b, 1, r, q] = gy

    return forward, backward


@functools.cache
def forward_warp_kernels(parallel: bool):
    """(forward, backward) of the prior-flow forward warp (eq. 9), for threads or one thread."""
    return _make_forward_warp(parallel)
