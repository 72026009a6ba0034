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

from losses._kernels import _exp, use_threads

__all__ = ["gru_kernels", "output_gate_kernels", "refiner_kernels", "use_threads"]

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

    # update_forward and update_backward open alike (the same per-plane views of q and hidden):
    # each kernel slices for itself, so that it reads alone next to its equation.
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
def output_gate_kernels(parallel: bool):
    """(forward, backward) of the ST-ConvGRU output gate, for threads or one thread."""
    return _make_output_gate(parallel)
