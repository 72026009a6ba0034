"""Compiled CPU kernels (numba) for the pointwise parts of the recurrent layers.

On CPU the networks run in channels-last layout (see ``agents/flownet.py``), where a (B, C, h, w)
tensor is a (B * h * w, C) matrix in memory. The gate arithmetic of a ConvGRU (eq. 4) and of the
ST-ConvGRU's output gate (eq. 6) then reads, for each pixel, a few contiguous runs of channels.
In torch each step of that arithmetic (add, sigmoid, product, tanh, ...) is its own pass over
memory through strided channel slices; here the whole update is one pass per pixel row, and its
backward is one more pass that recomputes the gates from the same inputs (nothing extra is kept).

The arithmetic runs in the inputs' dtype; for float32 the exponential is the vectorizable
polynomial of ``losses/_kernels.py`` (relative error < 1e-7), so results differ from torch's by a
few float32 ulps. The torch expressions in ``agents/layers.py`` are the reference the tests compare
against, and the path for CUDA and for other layouts.

Each forward kernel and its backward open with the same indexing of the gate columns: numba
compiles each kernel as one loop nest, so the shared preamble is written out in both.
"""

from __future__ import annotations

import functools

import numba
import numpy as np

from losses._kernels import _exp, use_threads

__all__ = ["deep_memory_up_kernel", "fused_refiner_kernel", "gru_kernels", "output_gate_kernels", "refiner_kernels", "use_threads"]

_OPTIONS = dict(nogil=True, cache=True, boundscheck=False, error_model="numpy",
                fastmath={"reassoc", "contract", "nsz"})


@numba.njit(inline="always", **_OPTIONS)
def _sigmoid(v, one):
    return one / (one + _exp(-v))


@numba.njit(inline="always", **_OPTIONS)
def _tanh(v, one):
    # tanh(v) = 1 - 2 / (e^(2v) + 1): exact limits +-1, absolute error a few ulps of 1.
    return one - (one + one) / (_exp(v + v) + one)


@numba.njit(inline="always", **_OPTIONS)
def _gru_forward(xr, xz, xh, hr, hz, hh, h, one):
    """eq. 4 for one channel of one pixel: the new hidden value."""
    r = _sigmoid(xr + hr, one)
    z = _sigmoid(xz + hz, one)
    c = _tanh(xh + r * hh, one)
    return h + z * (c - h)


@numba.njit(inline="always", **_OPTIONS)
def _gru_backward(xr, xz, xh, hr, hz, hh, h, g, one):
    """The gradient g of eq. 4's output taken back to (d/dX_r = d/dH_r, d/dX_z = d/dH_z,
    d/dX_h, d/dH_h, d/dH) for one channel of one pixel. With c = tanh(X_h + r H_h):
    d/dX_h = g z (1 - c^2), d/dH_h = r d/dX_h, d/dX_r = d/dX_h H_h r (1 - r),
    d/dX_z = g (c - H) z (1 - z), d/dH = g (1 - z)."""
    r = _sigmoid(xr + hr, one)
    z = _sigmoid(xz + hz, one)
    c = _tanh(xh + r * hh, one)
    d_h = g * z * (one - c * c)
    return d_h * hh * r * (one - r), g * (c - h) * z * (one - z), d_h, d_h * r, g * (one - z)


@numba.njit(inline="always", **_OPTIONS)
def _flat_offsets(e, n, width, xo):
    """Flat element e = p * n + q (pixel row p, channel q) -> (b, k): the offsets of channel q's
    r-gate entry in x_proj (rows of ``width``, columns from xo) and in h_proj (rows of 3n)."""
    p = e // n
    q = e - p * n
    return width * p + xo + q, 3 * n * p + q


def _make_gru(parallel: bool, n: int):
    """The ConvGRU update for hidden size ``n``, a compile-time constant here: one
    specialization per n (cached on disk like the rest). With n known, LLVM sees that the gate
    blocks j, n + j, 2n + j of a pixel row never overlap and vectorizes the loops (the backward
    is about 5x slower with a run-time n).

    Returns (forward, backward, forward_fresh, backward_fresh); the ``_fresh`` pair is for a
    zero hidden state (h_proj and hidden are neither read nor given). Arrays (P pixel rows):
    x_proj (P, >= xo + 3n), its columns xo .. xo + 3n the input-side convolutions [r, z,
    candidate] (several GRUs may share one x_proj at offsets xo); h_proj (P, 3n) the hidden-side
    convolutions; hidden, out, grad_out, grad_hidden (P, n); grad_x like x_proj (only its columns
    xo .. xo + 3n written); grad_h like h_proj.

    Two loop shapes: for n >= 8 each pixel row is taken as 1-D slices and the channel loop is
    vectorized (indexing x_proj[p, xo + j] directly, with xo known only at run time, keeps LLVM
    from vectorizing it: about 9x slower); for small n (the hidden size 2 of the flow refiners)
    the loop runs over the flat index e = p * n + j, which vectorizes across pixels. Each kernel
    holds a single parallel loop, and each flat view is its own statement: with numba 0.68 the
    parallel (not the serial) compile of the flat kernels gave wrong results while they held
    tuple assignments of several views (`a, b = x.reshape(-1), y.reshape(-1)`), in a first
    version also two parallel loops; which of the two was at fault was not separated (the tests
    compare every kernel, serial and parallel, with the torch expressions).
    """
    loop = numba.prange if parallel else range

    @numba.njit(parallel=parallel, **_OPTIONS)
    def forward_rows(x_proj, xo, h_proj, hidden, out):
        one = out.dtype.type(1.0)
        for p in loop(out.shape[0]):
            x = x_proj[p, xo : xo + 3 * n]
            hp = h_proj[p]
            h = hidden[p]
            o = out[p]
            for j in range(n):
                o[j] = _gru_forward(x[j], x[n + j], x[2 * n + j], hp[j], hp[n + j], hp[2 * n + j], h[j], one)

    @numba.njit(parallel=parallel, **_OPTIONS)
    def forward_rows_fresh(x_proj, xo, out):
        one = out.dtype.type(1.0)
        zero = one - one
        for p in loop(out.shape[0]):
            x = x_proj[p, xo : xo + 3 * n]
            o = out[p]
            for j in range(n):
                o[j] = _gru_forward(x[j], x[n + j], x[2 * n + j], zero, zero, zero, zero, one)

    @numba.njit(parallel=parallel, **_OPTIONS)
    def backward_rows(x_proj, xo, h_proj, hidden, grad_out, grad_x, grad_h, grad_hidden):
        one = grad_out.dtype.type(1.0)
        for p in loop(grad_out.shape[0]):
            x = x_proj[p, xo : xo + 3 * n]
            gx = grad_x[p, xo : xo + 3 * n]
            hp = h_proj[p]
            gh = grad_h[p]
            h = hidden[p]
            g = grad_out[p]
            ghid = grad_hidden[p]
            for j in range(n):
                d_r, d_z, d_c, d_hh, d_h = _gru_backward(
                    x[j], x[n + j], x[2 * n + j], hp[j], hp[n + j], hp[2 * n + j], h[j], g[j], one
                )
                gx[j] = d_r
                gx[n + j] = d_z
                gx[2 * n + j] = d_c
                gh[j] = d_r
                gh[n + j] = d_z
                gh[2 * n + j] = d_hh
                ghid[j] = d_h

    @numba.njit(parallel=parallel, **_OPTIONS)
    def backward_rows_fresh(x_proj, xo, grad_out, grad_x):
        one = grad_out.dtype.type(1.0)
        zero = one - one
        for p in loop(grad_out.shape[0]):
            x = x_proj[p, xo : xo + 3 * n]
            gx = grad_x[p, xo : xo + 3 * n]
            g = grad_out[p]
            for j in range(n):
                d_r, d_z, d_c, _, _ = _gru_backward(
                    x[j], x[n + j], x[2 * n + j], zero, zero, zero, zero, g[j], one
                )
                gx[j] = d_r
                gx[n + j] = d_z
                gx[2 * n + j] = d_c

    @numba.njit(parallel=parallel, **_OPTIONS)
    def forward_flat(x_proj, xo, h_proj, hidden, out):
        width = x_proj.shape[1]
        xf = x_proj.reshape(-1)
        hf = h_proj.reshape(-1)
        hid = hidden.reshape(-1)
        of = out.reshape(-1)
        one = out.dtype.type(1.0)
        for e in loop(of.shape[0]):
            b, k = _flat_offsets(e, n, width, xo)
            of[e] = _gru_forward(xf[b], xf[b + n], xf[b + 2 * n], hf[k], hf[k + n], hf[k + 2 * n], hid[e], one)

    @numba.njit(parallel=parallel, **_OPTIONS)
    def forward_flat_fresh(x_proj, xo, out):
        width = x_proj.shape[1]
        xf = x_proj.reshape(-1)
        of = out.reshape(-1)
        one = out.dtype.type(1.0)
        zero = one - one
        for e in loop(of.shape[0]):
            b, _ = _flat_offsets(e, n, width, xo)
            of[e] = _gru_forward(xf[b], xf[b + n], xf[b + 2 * n], zero, zero, zero, zero, one)

    @numba.njit(parallel=parallel, **_OPTIONS)
    def backward_flat(x_proj, xo, h_proj, hidden, grad_out, grad_x, grad_h, grad_hidden):
        width = x_proj.shape[1]
        xf = x_proj.reshape(-1)
        hf = h_proj.reshape(-1)
        hid = hidden.reshape(-1)
        gf = grad_out.reshape(-1)
        gxf = grad_x.reshape(-1)
        ghf = grad_h.reshape(-1)
        ghidf = grad_hidden.reshape(-1)
        one = grad_out.dtype.type(1.0)
        for e in loop(gf.shape[0]):
            b, k = _flat_offsets(e, n, width, xo)
            d_r, d_z, d_c, d_hh, d_h = _gru_backward(
                xf[b], xf[b + n], xf[b + 2 * n], hf[k], hf[k + n], hf[k + 2 * n], hid[e], gf[e], one
            )
            gxf[b] = d_r
            gxf[b + n] = d_z
            gxf[b + 2 * n] = d_c
            ghf[k] = d_r
            ghf[k + n] = d_z
            ghf[k + 2 * n] = d_hh
            ghidf[e] = d_h

    @numba.njit(parallel=parallel, **_OPTIONS)
    def backward_flat_fresh(x_proj, xo, grad_out, grad_x):
        width = x_proj.shape[1]
        xf = x_proj.reshape(-1)
        gf = grad_out.reshape(-1)
        gxf = grad_x.reshape(-1)
        one = grad_out.dtype.type(1.0)
        zero = one - one
        for e in loop(gf.shape[0]):
            b, _ = _flat_offsets(e, n, width, xo)
            d_r, d_z, d_c, _, _ = _gru_backward(
                xf[b], xf[b + n], xf[b + 2 * n], zero, zero, zero, zero, gf[e], one
            )
            gxf[b] = d_r
            gxf[b + n] = d_z
            gxf[b + 2 * n] = d_c

    if n >= 8:
        return forward_rows, backward_rows, forward_rows_fresh, backward_rows_fresh
    return forward_flat, backward_flat, forward_flat_fresh, backward_flat_fresh


def _make_refiner(parallel: bool, n: int):
    """The flow refiner of FGD-Net (eq. 11, ``u = ConvGRU_flow(tanh(a), ubar)``, hidden size n)
    around one merged convolution. With the ConvGRU's input X = tanh(a) and hidden state
    H = ubar side by side as one 2n-channel image, its four convolutions [Wxr*X + Whr*H,
    Wxz*X + Whz*H, Wxh*X, Whh*H] are one convolution with 4n outputs, which for n = 2 runs about
    twice as fast as the two 3n-output convolutions of :class:`~agents.layers.ConvGRU` (at two
    channels oneDNN's cost is per pixel, not per multiply). At these channel counts the work is
    planar (NCHW): a pixel-major layout would leave only 2-wide loops, which do not vectorize.

    Returns (pack_forward, pack_backward, update_forward, update_backward). Arrays (B images of
    P pixels): pack: a (B, P, n) pixel rows (a channels-last head output), hidden (B, n, P) ->
    packed (B, 2n, P) = [tanh(a), hidden]; its backward takes grad_packed (B, 2n, P) to grad_a
    (B, P, n) (the hidden half is the caller's). update: q (B, 4n, P) the merged convolution,
    hidden (B, n, P) -> out (B, n, P), eq. 4 with r = sig(q_r), z = sig(q_z), Hhat = tanh(q_x +
    r . q_h); its backward gives grad_q (B, 4n, P) and grad_hidden (B, n, P) (the direct 1 - z
    path only). One parallel loop over the B * n channel planes each.
    """
    loop = numba.prange if parallel else range

    @numba.njit(parallel=parallel, **_OPTIONS)
    def pack_forward(a, hidden, packed):
        one = packed.dtype.type(1.0)
        for task in loop(a.shape[0] * n):
            b = task // n
            j = task - b * n
            source = a[b, :, j]
            dest = packed[b, j]
            for i in range(source.shape[0]):  # the strided gather first, then a vector loop
                dest[i] = source[i]
            for i in range(dest.shape[0]):
                dest[i] = _tanh(dest[i], one)
            packed[b, n + j] = hidden[b, j]

    @numba.njit(parallel=parallel, **_OPTIONS)
    def pack_backward(packed, grad_packed, grad_a):
        one = grad_a.dtype.type(1.0)
        for task in loop(grad_a.shape[0] * n):
            b = task // n
            j = task - b * n
            t = packed[b, j]
            g = grad_packed[b, j]
            dest = grad_a[b, :, j]
            for i in range(t.shape[0]):
                dest[i] = g[i] * (one - t[i] * t[i])

    @numba.njit(parallel=parallel, **_OPTIONS)
    def update_forward(q, hidden, out):
        one = out.dtype.type(1.0)
        zero = one - one
        for task in loop(out.shape[0] * n):
            b = task // n
            j = task - b * n
            q_r = q[b, j]
            q_z = q[b, n + j]
            q_x = q[b, 2 * n + j]
            q_h = q[b, 3 * n + j]
            h = hidden[b, j]
            o = out[b, j]
            for i in range(o.shape[0]):
                o[i] = _gru_forward(q_r[i], q_z[i], q_x[i], zero, zero, q_h[i], h[i], one)

    @numba.njit(parallel=parallel, **_OPTIONS)
    def update_backward(q, hidden, grad_out, grad_q, grad_hidden):
        one = grad_out.dtype.type(1.0)
        zero = one - one
        for task in loop(grad_out.shape[0] * n):
            b = task // n
            j = task - b * n
            q_r = q[b, j]
            q_z = q[b, n + j]
            q_x = q[b, 2 * n + j]
            q_h = q[b, 3 * n + j]
            h = hidden[b, j]
            g = grad_out[b, j]
            g_r = grad_q[b, j]
            g_z = grad_q[b, n + j]
            g_x = grad_q[b, 2 * n + j]
            g_h = grad_q[b, 3 * n + j]
            g_hidden = grad_hidden[b, j]
            for i in range(g.shape[0]):
                d_r, d_z, d_c, d_hh, d_h = _gru_backward(
                    q_r[i], q_z[i], q_x[i], zero, zero, q_h[i], h[i], g[i], one
                )
                g_r[i] = d_r
                g_z[i] = d_z
                g_x[i] = d_c
                g_h[i] = d_hh
                g_hidden[i] = d_h

    return pack_forward, pack_backward, update_forward, update_backward


def _make_fused_refiner(parallel: bool, n: int):
    """The whole flow refiner of FGD-Net (eqs. 10-11) in one call, for inference (no backward):
    ``u = ConvGRU_flow(tanh(a), ubar)`` with the merged 3x3 convolution of
    :func:`_make_refiner` computed here as well, row by row, instead of by oneDNN between two
    passes. At 2n = 4 input and 4n = 8 output channels oneDNN's convolution costs about as much
    as the passes around it, and at batch 8 torch falls back to its slow convolution for the
    small scales; here the padded input rows of one output row stay in cache and its 4n
    pre-activation rows are consumed by eq. 4 straight away.

    Arrays: a (B, h, w, n) the channels-last head output; hidden (B, n, h, w) the prior ubar;
    weight (4n, 2n, 3, 3) and bias (4n) the merged convolution (zero padding 1); out (B, n, h, w).
    Two parallel loops over the B * h rows: [tanh(a), ubar] into a zero-bordered planar buffer,
    then the convolution (a 9-tap vector loop per input channel and output row) and eq. 4.
    """
    loop = numba.prange if parallel else range
    m = 2 * n
    k = 4 * n

    @numba.njit(parallel=parallel, **_OPTIONS)
    def fused_forward(a, hidden, weight, bias, out):
        batch, height, width = out.shape[0], out.shape[2], out.shape[3]
        one = out.dtype.type(1.0)
        zero = one - one
        padded = np.empty((batch, m, height + 2, width + 2), dtype=out.dtype)
        for task in loop(batch * height):
            b = task // height
            y = task - b * height
            for c in range(m):
                padded[b, c, y + 1, 0] = zero
                padded[b, c, y + 1, width + 1] = zero
                if y == 0:  # the zero row above the first
                    for x in range(width + 2):
                        padded[b, c, 0, x] = zero
                if y == height - 1:  # and below the last
                    for x in range(width + 2):
                        padded[b, c, height + 1, x] = zero
            for j in range(n):
                row = padded[b, j, y + 1]
                for x in range(width):  # the strided gather first, then a vector loop
                    row[x + 1] = a[b, y, x, j]
                for x in range(1, width + 1):
                    row[x] = _tanh(row[x], one)
                row = padded[b, n + j, y + 1]
                h = hidden[b, j, y]
                for x in range(width):
                    row[x + 1] = h[x]
        for task in loop(batch * height):
            b = task // height
            y = task - b * height
            q = np.empty((k, width), dtype=out.dtype)
            for o in range(k):
                q_o = q[o]
                for x in range(width):
                    q_o[x] = bias[o]
                for c in range(m):
                    s0, s1, s2 = padded[b, c, y], padded[b, c, y + 1], padded[b, c, y + 2]
                    w = weight[o, c]
                    w00, w01, w02 = w[0, 0], w[0, 1], w[0, 2]
                    w10, w11, w12 = w[1, 0], w[1, 1], w[1, 2]
                    w20, w21, w22 = w[2, 0], w[2, 1], w[2, 2]
                    for x in range(width):
                        q_o[x] += (
                            w00 * s0[x] + w01 * s0[x + 1] + w02 * s0[x + 2]
                            + w10 * s1[x] + w11 * s1[x + 1] + w12 * s1[x + 2]
                            + w20 * s2[x] + w21 * s2[x + 1] + w22 * s2[x + 2]
                        )
            for j in range(n):
                q_r, q_z, q_x, q_h = q[j], q[n + j], q[2 * n + j], q[3 * n + j]
                h = hidden[b, j, y]
                o_row = out[b, j, y]
                for x in range(width):
                    o_row[x] = _gru_forward(q_r[x], q_z[x], q_x[x], zero, zero, q_h[x], h[x], one)

    return fused_forward


def _make_deep_memory_up(parallel: bool):
    """``M = relu(conv3x3(upsample_bilinear(S4)))`` from the convolution's 9 taps already applied
    at low resolution (see :class:`~agents.evmgrflownet.DeepMemoryUp`), for inference: the tap
    shift and the bilinear upsampling (2 source rows and 2 source columns per output pixel) as two
    gather passes instead of dense matrix products, and the relu, in one call.

    Arrays: taps (B, h, w, 3, 3, O) (the channels-last output of the tap convolution); per output
    row Y + i of the shifted grid (index Y + i for tap row i, i.e. position Y + i - 1, H + 2
    entries) the source rows row0/row1 and weights rw0/rw1 (zero off the image: the convolution's
    zero padding), likewise col0/col1/cw0/cw1 for the W + 2 columns; half (B, 3, h, W, O) scratch;
    out (B, H, W, O), the channels-last M.
    """
    loop = numba.prange if parallel else range

    @numba.njit(parallel=parallel, **_OPTIONS)
    def forward(taps, row0, row1, rw0, rw1, col0, col1, cw0, cw1, half, out):
        batch, low_h = taps.shape[0], taps.shape[1]
        height, width, channels = out.shape[1], out.shape[2], out.shape[3]
        zero = out.dtype.type(0.0)  # typed: a Python 0.0 would promote float32 loops to float64
        for task in loop(batch * 3 * low_h):  # columns: half[b, i, y, X] = sum_j C_j[X] T[b, y, :, i, j]
            b = task // (3 * low_h)
            i = (task // low_h) % 3
            y = task % low_h
            for x in range(width):
                dest = half[b, i, y, x]
                for o in range(channels):
                    dest[o] = zero
                for j in range(3):
                    k = x + j
                    a0, a1 = cw0[k], cw1[k]
                    s0 = taps[b, y, col0[k], i, j]
                    s1 = taps[b, y, col1[k], i, j]
                    for o in range(channels):
                        dest[o] += a0 * s0[o] + a1 * s1[o]
        for task in loop(batch * height):  # rows: M[b, Y] = relu(sum_i R_i[Y] half[b, i])
            b = task // height
            y = task - b * height
            dest = out[b, y]
            for x in range(width):
                for o in range(channels):
                    dest[x, o] = zero
            for i in range(3):
                k = y + i
                a0, a1 = rw0[k], rw1[k]
                s0 = half[b, i, row0[k]]
                s1 = half[b, i, row1[k]]
                for x in range(width):
                    for o in range(channels):
                        dest[x, o] += a0 * s0[x, o] + a1 * s1[x, o]
            for x in range(width):
                for o in range(channels):
                    dest[x, o] = max(dest[x, o], zero)

    return forward


def _make_output_gate(parallel: bool):
    loop = numba.prange if parallel else range

    @numba.njit(parallel=parallel, **_OPTIONS)
    def forward(gate_x, gate_h, fusion, out):
        """ST-ConvGRU output (eq. 6): ``out = sig(gate_x + gate_h) tanh(fusion)``, all (P, n)."""
        P, n = out.shape
        one = out.dtype.type(1.0)
        for p in loop(P):
            for j in range(n):
                out[p, j] = _sigmoid(gate_x[p, j] + gate_h[p, j], one) * _tanh(fusion[p, j], one)

    @numba.njit(parallel=parallel, **_OPTIONS)
    def backward(gate_x, gate_h, fusion, grad_out, grad_gate, grad_fusion):
        """grad_gate (P, n): the gradient for gate_x and for gate_h (the same); grad_fusion (P, n)."""
        P, n = grad_out.shape
        one = grad_out.dtype.type(1.0)
        for p in loop(P):
            for j in range(n):
                o = _sigmoid(gate_x[p, j] + gate_h[p, j], one)
                t = _tanh(fusion[p, j], one)
                g = grad_out[p, j]
                grad_gate[p, j] = g * t * o * (one - o)
                grad_fusion[p, j] = g * o * (one - t * t)

    return forward, backward


@functools.cache
def gru_kernels(parallel: bool, hidden_size: int):
    """(forward, backward, forward_fresh, backward_fresh) of the ConvGRU update of
    ``hidden_size`` channels, for threads (``parallel``) or one thread (see :func:`_make_gru`)."""
    return _make_gru(parallel, int(hidden_size))


@functools.cache
def refiner_kernels(parallel: bool, hidden_size: int):
    """(pack_forward, pack_backward, update_forward, update_backward) of the merged-convolution
    flow refiner of ``hidden_size`` channels (see :func:`_make_refiner`)."""
    return _make_refiner(parallel, int(hidden_size))


@functools.cache
def fused_refiner_kernel(parallel: bool, hidden_size: int):
    """The inference-only flow refiner of ``hidden_size`` channels (see
    :func:`_make_fused_refiner`), for threads or one thread."""
    return _make_fused_refiner(parallel, int(hidden_size))


@functools.cache
def deep_memory_up_kernel(parallel: bool):
    """The inference-only tap shift + upsampling + relu of ``DeepMemoryUp`` (see
    :func:`_make_deep_memory_up`), for threads or one thread."""
    return _make_deep_memory_up(parallel)


@functools.cache
def output_gate_kernels(parallel: bool):
    """(forward, backward) of the ST-ConvGRU output gate, for threads or one thread."""
    return _make_output_gate(parallel)
