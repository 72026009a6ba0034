"""Tests for losses/: a slow, obvious float64 reference (explicit loops over events) is the
oracle for the fast batched code; plus gradients, behaviour on an analytic translating pattern,
and bad input."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from losses import (
    EventBatch,
    LossWeights,
    accumulated_hmc_loss,
    at_loss,
    bilinear_splat,
    event_pixel_mask,
    forward_warp_flow,
    hmc_loss,
    image_terms,
    sample_flow,
    smoothness,
    warp,
    warped_event_images,
    window_loss,
    zero_flow_loss,
)

RTOL = 1e-6


@pytest.fixture(params=["compiled", "torch"])
def backend(request, monkeypatch):
    """Run a test through the compiled CPU kernels (the default on CPU) and through the torch
    path (CUDA's, and CPU's without numba): both must match the slow reference."""
    if request.param == "torch":
        monkeypatch.setattr(image_terms, "_kernels", None)
        monkeypatch.setattr(smoothness, "_kernels", None)
        monkeypatch.setattr(warp, "_kernels", None)
    return request.param

# --------------------------------------------------------------------------------------------
# Slow reference: one event at a time, float64, kernel written as in docs/method.md, "Losses".
# --------------------------------------------------------------------------------------------


def ref_kernel_image(xw, yw, H, W):
    """k(q - xw, r - yw) over all pixels (H, W): max(0, 1-|dx|) * max(0, 1-|dy|)."""
    kx = np.maximum(0.0, 1.0 - np.abs(np.arange(W) - xw))
    ky = np.maximum(0.0, 1.0 - np.abs(np.arange(H) - yw))
    return np.outer(ky, kx)


def ref_sample(flow, x, y):
    """flow (2, H, W); coordinates clamped to the image, then bilinear."""
    _, H, W = flow.shape
    k = ref_kernel_image(min(max(x, 0.0), W - 1), min(max(y, 0.0), H - 1), H, W)
    return np.array([(k * flow[0]).sum(), (k * flow[1]).sum()])


def ref_images(flow, x, y, tau, p, s, H, W, span=1.0, t_override=None, flows_per_event=None):
    C = np.zeros((2, H, W))
    A = np.zeros((2, H, W))
    for i in range(len(x)):
        u = ref_sample(flow if flows_per_event is None else flows_per_event[i], x[i], y[i])
        t = tau[i] if t_override is None else t_override[i]
        xw, yw = x[i] + (s - t) * u[0], y[i] + (s - t) * u[1]
        k = ref_kernel_image(xw, yw, H, W)
        P = 0 if p[i] > 0 else 1
        C[P] += k
        A[P] += k * (1.0 - abs(s - t) / span)
    return C, A


def ref_at(C, A):
    T = A / (C + 1e-9)
    nnz = np.count_nonzero(C[0] + C[1] > 0)
    return (T**2).sum() / (nnz + 1e-9)


def ref_ec(C, alpha=0.6):
    N = C.shape[1] * C.shape[2]
    return N / np.exp(-alpha * C[0]).sum() + N / np.exp(-alpha * C[1]).sum() - 2


def ref_smooth(flow, x, y, scaling, eps=1e-3):
    _, H, W = flow.shape
    has = np.zeros((H, W), bool)
    for xi, yi in zip(x, y):
        c, r = int(np.round(xi)), int(np.round(yi))
        if 0 <= c < W and 0 <= r < H:
            has[r, c] = True
    f = flow / scaling
    total = 0.0
    for dr, dc, _ in ((0, 1, 0), (1, 0, 0), (1, 1, 0), (-1, 1, 1)):  # right, down, d-right, up-right
        for r in range(H):
            for c in range(W):
                r2, c2 = r + dr, c + dc
                if 0 <= r2 < H and 0 <= c2 < W and has[r, c] and has[r2, c2]:
                    for comp in range(2):
                        d = f[comp, r2, c2] - f[comp, r, c]
                        total += math.sqrt(d * d + eps * eps)
    return total / 4


def ref_hmc(flow, x, y, tau, p, lambda_1=1.0, lambda_2=1e-3, alpha=0.6, scaling=None, use_ec=True):
    _, H, W = flow.shape
    scaling = max(H, W) if scaling is None else scaling
    at = ec = 0.0
    for s in (0.0, 1.0):
        C, A = ref_images(flow, x, y, tau, p, s, H, W)
        at += ref_at(C, A)
        ec += ref_ec(C, alpha)
    sm = ref_smooth(flow, x, y, scaling)
    total = at + lambda_2 * sm + (lambda_1 * ec if use_ec else 0.0)
    return total, at, ec, sm


# --------------------------------------------------------------------------------------------
# Random windows
# --------------------------------------------------------------------------------------------


def random_window(rng, n, H, W, *, integer=True, border=False, polarity="both", t0=1000, dur=5000):
    if border:  # hug the border: first/last rows and columns
        x = rng.choice([0, 1, W - 2, W - 1], n).astype(float)
        y = rng.integers(0, H, n).astype(float)
        if not integer:
            x = np.clip(x + rng.uniform(-0.4, 0.4, n), 0, W - 1)
    else:
        x = rng.integers(0, W, n).astype(float) if integer else rng.uniform(0, W - 1, n)
        y = rng.integers(0, H, n).astype(float) if integer else rng.uniform(0, H - 1, n)
    t = np.sort(rng.integers(t0, t0 + dur + 1, n))  # t == t_end allowed (tau = 1)
    if polarity == "both":
        p = rng.choice([-1, 1], n)
    else:
        p = np.full(n, 1 if polarity == "on" else -1)
    return dict(x=x, y=y, t=t, p=p, t_start=t0, t_end=t0 + dur)


def taus(w):
    return (w["t"] - w["t_start"]) / (w["t_end"] - w["t_start"])


CASES = [
    # (n events, H, W, integer coords, near border, polarity, flow magnitude)
    (0, 9, 11, True, False, "both", 2.0),
    (1, 9, 11, True, False, "both", 2.0),
    (40, 9, 11, True, False, "both", 2.0),
    (60, 12, 8, False, False, "both", 3.0),
    (50, 10, 13, True, True, "both", 4.0),
    (50, 10, 13, False, True, "on", 4.0),
    (30, 7, 7, True, False, "off", 0.7),
    (120, 16, 20, False, False, "both", 6.0),
]


@pytest.mark.parametrize("case", CASES, ids=[f"case{i}" for i in range(len(CASES))])
def test_hmc_matches_slow_reference(case, backend):
    n, H, W, integer, border, pol, mag = case
    rng = np.random.default_rng(n * 7 + H)
    w = random_window(rng, n, H, W, integer=integer, border=border, polarity=pol)
    flow = rng.normal(0, mag, (2, H, W))
    ev = EventBatch.from_windows([w], dtype=torch.float64)
    out = hmc_loss(torch.from_numpy(flow)[None], ev)
    total, at, ec, sm = ref_hmc(flow, w["x"], w["y"], taus(w), w["p"])
    np.testing.assert_allclose(out.loss.item(), total, rtol=RTOL, atol=1e-12)
    np.testing.assert_allclose(out.components["at"].item(), at, rtol=RTOL, atol=1e-12)
    np.testing.assert_allclose(out.components["ec"].item(), ec, rtol=RTOL, atol=1e-12)
    np.testing.assert_allclose(out.components["smooth"].item(), sm, rtol=RTOL, atol=1e-12)
    # baseline loss: same terms without L_EC
    out_at = at_loss(torch.from_numpy(flow)[None], ev)
    np.testing.assert_allclose(out_at.loss.item(), at + 1e-3 * sm, rtol=RTOL, atol=1e-12)


def test_padded_batch_equals_per_sample_results(backend):
    rng = np.random.default_rng(1)
    H, W = 10, 12
    wins = [
        random_window(rng, 35, H, W),
        random_window(rng, 0, H, W),
        random_window(rng, 80, H, W, integer=False),
        random_window(rng, 5, H, W, border=True, polarity="on"),
    ]
    flow = torch.from_numpy(rng.normal(0, 2.5, (4, 2, H, W)))
    batch = hmc_loss(flow, EventBatch.from_windows(wins, dtype=torch.float64))
    singles = [hmc_loss(flow[b : b + 1], EventBatch.from_windows([w], dtype=torch.float64))
               for b, w in enumerate(wins)]
    for b, (w, single) in enumerate(zip(wins, singles)):
        total = ref_hmc(flow[b].numpy(), w["x"], w["y"], taus(w), w["p"])[0]
        np.testing.assert_allclose(batch.per_sample[b].item(), total, rtol=RTOL, atol=1e-12)
        np.testing.assert_allclose(batch.per_sample[b].item(), single.loss.item(), rtol=1e-12)
        for k in ("at", "ec", "smooth"):
            np.testing.assert_allclose(batch.components[k][b].item(),
                                       single.components[k][0].item(), rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(batch.loss.item(), np.mean([s.loss.item() for s in singles]), rtol=1e-12)


def test_non_default_weights_and_scaling_match_reference(backend):
    rng = np.random.default_rng(5)
    H, W = 8, 9
    w = random_window(rng, 40, H, W, integer=False)
    flow = rng.normal(0, 2, (2, H, W))
    ev = EventBatch.from_windows([w], dtype=torch.float64)
    out = hmc_loss(torch.from_numpy(flow)[None], ev, lambda_1=0.3, lambda_2=0.5, alpha=1.1,
                   flow_scaling=3.0)
    total = ref_hmc(flow, w["x"], w["y"], taus(w), w["p"], 0.3, 0.5, 1.1, 3.0)[0]
    np.testing.assert_allclose(out.loss.item(), total, rtol=RTOL)


def test_multiscale_is_mean_of_upsampled_scales():
    rng = np.random.default_rng(2)
    H, W = 16, 12
    w = random_window(rng, 70, H, W, integer=False)
    ev = EventBatch.from_windows([w], dtype=torch.float64)
    scales = [torch.from_numpy(rng.normal(0, 2, (1, 2, H // f, W // f))) for f in (4, 2, 1)]
    out = hmc_loss(scales, ev)
    expected = []
    for f in scales:
        up = torch.nn.functional.interpolate(f, size=(H, W), mode="bilinear", align_corners=False)
        expected.append(ref_hmc(up[0].numpy(), w["x"], w["y"], taus(w), w["p"])[0])
    np.testing.assert_allclose(out.loss.item(), np.mean(expected), rtol=RTOL)
    # a constant coarse flow upsamples to the same constant: values are not rescaled
    const = torch.full((1, 2, H // 4, W // 4), 1.5, dtype=torch.float64)
    full = torch.full((1, 2, H, W), 1.5, dtype=torch.float64)
    np.testing.assert_allclose(hmc_loss([const, full], ev).loss.item(),
                               hmc_loss(full, ev).loss.item(), rtol=1e-12)


def test_accumulated_matches_reference_and_reduces_to_per_window(backend):
    rng = np.random.default_rng(3)
    H, W, K = 9, 10, 3
    wins = [random_window(rng, n, H, W, integer=False) for n in (20, 0, 30)]
    flows = [rng.normal(0, 1.5, (2, H, W)) for _ in range(K)]
    evs = [EventBatch.from_windows([w], dtype=torch.float64) for w in wins]
    out = accumulated_hmc_loss([torch.from_numpy(f)[None] for f in flows], evs)
    x = np.concatenate([w["x"] for w in wins])
    y = np.concatenate([w["y"] for w in wins])
    p = np.concatenate([w["p"] for w in wins])
    T = np.concatenate([k + taus(w) for k, w in enumerate(wins)])
    per_event_flow = [flows[k] for k, w in enumerate(wins) for _ in range(len(w["x"]))]
    at = ec = 0.0
    for s in (0.0, float(K)):
        C, A = ref_images(None, x, y, None, p, s, H, W, span=K, t_override=T,
                          flows_per_event=per_event_flow)
        at += ref_at(C, A)
        ec += ref_ec(C)
    sm = np.mean([ref_smooth(f, w["x"], w["y"], max(H, W)) for f, w in zip(flows, wins)])
    np.testing.assert_allclose(out.loss.item(), at + ec + 1e-3 * sm, rtol=RTOL)
    single = accumulated_hmc_loss([torch.from_numpy(flows[0])[None]], evs[:1])
    np.testing.assert_allclose(single.loss.item(),
                               hmc_loss(torch.from_numpy(flows[0])[None], evs[0]).loss.item(),
                               rtol=1e-12)


def ref_at_sum(C, A):
    """Eq. 14 as printed: the bare sum of squared average timestamps."""
    return ((A / (C + 1e-9)) ** 2).sum()


def ref_terms_at(flow_of_event, x, y, T, p, refs, span, H, W, at_of=ref_at):
    """sum over the two references of L_AT and of L_EC, events warped to any reference times
    with closeness 1 - |s - T| / span."""
    at = ec = 0.0
    for s in refs:
        C, A = ref_images(None, x, y, None, p, s, H, W, span=span, t_override=T, flows_per_event=flow_of_event)
        at += at_of(C, A)
        ec += ref_ec(C)
    return at, ec


@pytest.mark.parametrize("reference_times", ["window", "events"])
@pytest.mark.parametrize("at_normalisation", ["event_pixels", "sum"])
def test_loss_options_match_slow_reference(backend, reference_times, at_normalisation):
    """The readings the paper leaves open, each against the slow reference: references at the
    window bounds or at the first and last event (closeness over their span, the flow still in
    pixels per window), L_AT over N_nz or eq. 14's bare sum, coarse scales upsampled nearest."""
    rng = np.random.default_rng(11)
    H, W = 12, 16
    w = random_window(rng, 50, H, W, integer=False)
    w["t"] = np.sort(rng.integers(2000, 4500, 50))  # first/last event well inside [1000, 6000]
    tau = taus(w)
    coarse = rng.normal(0, 2, (2, H // 4, W // 4))
    fine = rng.normal(0, 2, (2, H, W))
    nearest = np.repeat(np.repeat(coarse, 4, axis=1), 4, axis=2)  # each cell over its 4x4 pixels
    ev = EventBatch.from_windows([w], dtype=torch.float64)
    out = hmc_loss([torch.from_numpy(coarse)[None], torch.from_numpy(fine)[None]], ev, upsampling="nearest",
                   reference_times=reference_times, at_normalisation=at_normalisation)
    refs, span = ((0.0, 1.0), 1.0) if reference_times == "window" else ((tau.min(), tau.max()), tau.max() - tau.min())
    at_of = ref_at if at_normalisation == "event_pixels" else ref_at_sum
    expected = []
    for flow in (nearest, fine):
        at, ec = ref_terms_at([flow] * len(tau), w["x"], w["y"], tau, w["p"], refs, span, H, W, at_of)
        expected.append(at + ec + 1e-3 * ref_smooth(flow, w["x"], w["y"], max(H, W)))
    np.testing.assert_allclose(out.loss.item(), np.mean(expected), rtol=RTOL)
    if reference_times == "events" and at_normalisation == "sum":
        assert out.loss.item() != pytest.approx(hmc_loss([torch.from_numpy(coarse)[None], torch.from_numpy(fine)[None]],
                                                         ev, upsampling="nearest").loss.item(), rel=1e-3)


def test_accumulated_per_scale_and_event_references_match_reference(backend):
    """Sequential learning with per-scale flows: scale j of every window forms one accumulated
    loss, the scales are averaged; with reference_times "events" the references sit at the first
    event of the first window and the last of the last."""
    rng = np.random.default_rng(12)
    H, W, K = 8, 8, 3
    wins = [random_window(rng, n, H, W, integer=False) for n in (15, 25, 20)]
    flows = [[rng.normal(0, 1.0, (2, H // 2, W // 2)), rng.normal(0, 1.0, (2, H, W))] for _ in range(K)]
    evs = [EventBatch.from_windows([w], dtype=torch.float64) for w in wins]
    x = np.concatenate([w["x"] for w in wins])
    y = np.concatenate([w["y"] for w in wins])
    p = np.concatenate([w["p"] for w in wins])
    T = np.concatenate([k + taus(w) for k, w in enumerate(wins)])
    for reference_times in ("window", "events"):
        out = accumulated_hmc_loss([[torch.from_numpy(f)[None] for f in per] for per in flows], evs,
                                   reference_times=reference_times)
        if reference_times == "window":
            refs, span = (0.0, float(K)), float(K)
        else:
            refs, span = (T.min(), T.max()), T.max() - T.min()
        expected = []
        for j in range(2):
            full = [np.asarray(torch.nn.functional.interpolate(torch.from_numpy(per[j])[None], size=(H, W),
                                                               mode="bilinear", align_corners=False)[0])
                    for per in flows]
            per_event = [full[k] for k, w in enumerate(wins) for _ in range(len(w["x"]))]
            at, ec = ref_terms_at(per_event, x, y, T, p, refs, span, H, W)
            sm = np.mean([ref_smooth(f, w["x"], w["y"], max(H, W)) for f, w in zip(full, wins)])
            expected.append(at + ec + 1e-3 * sm)
        np.testing.assert_allclose(out.loss.item(), np.mean(expected), rtol=RTOL)


def test_loss_options_refuse_unknown_choices():
    ev, (H, W) = _small_batch()
    flow = torch.zeros(2, 2, H, W)
    for option in ("upsampling", "reference_times", "at_normalisation"):
        with pytest.raises(ValueError, match=option):
            hmc_loss(flow, ev, **{option: "bicubic"})
        with pytest.raises(ValueError, match=option):
            accumulated_hmc_loss([flow], [ev], **{option: "bicubic"})


# --------------------------------------------------------------------------------------------
# Building blocks
# --------------------------------------------------------------------------------------------


def test_sample_flow_exact_at_integers_and_matches_reference(backend):
    rng = np.random.default_rng(4)
    H, W = 7, 9
    flow = rng.normal(0, 3, (2, H, W)).astype(np.float32)
    xi = rng.integers(0, W, 50)
    yi = rng.integers(0, H, 50)
    got = sample_flow(torch.from_numpy(flow)[None], torch.tensor(xi, dtype=torch.float32)[None],
                      torch.tensor(yi, dtype=torch.float32)[None])[0].numpy()
    np.testing.assert_array_equal(got, flow[:, yi, xi].T)  # bit-exact in float32
    xs = rng.uniform(-2, W + 1, 60)  # includes off-image points: border clamp
    ys = rng.uniform(-2, H + 1, 60)
    got = sample_flow(torch.from_numpy(flow.astype(np.float64))[None], torch.from_numpy(xs)[None],
                      torch.from_numpy(ys)[None])[0].numpy()
    want = np.stack([ref_sample(flow.astype(np.float64), a, b) for a, b in zip(xs, ys)])
    np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-12)


def test_bilinear_splat_matches_reference_and_drops_outside_corners():
    rng = np.random.default_rng(6)
    H, W, N = 6, 8, 40
    x = rng.uniform(-1.5, W + 0.5, (2, N))
    y = rng.uniform(-1.5, H + 0.5, (2, N))
    vals = rng.normal(size=(2, N, 3))
    mask = rng.random((2, N)) > 0.2
    got = bilinear_splat(*(torch.from_numpy(a) for a in (x, y, vals)), H, W,
                         mask=torch.from_numpy(mask)).numpy()
    want = np.zeros((2, 3, H, W))
    for b in range(2):
        for i in range(N):
            if mask[b, i]:
                want[b] += ref_kernel_image(x[b, i], y[b, i], H, W)[None] * vals[b, i][:, None, None]
    np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-12)
    # an event half outside keeps only its in-image weight
    one = bilinear_splat(torch.tensor([[-0.25]]), torch.tensor([[2.0]]), torch.ones(1, 1, 1), H, W)
    assert one.sum().item() == pytest.approx(0.75)


def test_warped_event_images_match_reference():
    rng = np.random.default_rng(8)
    H, W = 9, 11
    wins = [random_window(rng, 40, H, W, integer=False), random_window(rng, 25, H, W, border=True)]
    ev = EventBatch.from_windows(wins, dtype=torch.float64)
    flow = rng.normal(0, 2, (2, 2, H, W))
    u = sample_flow(torch.from_numpy(flow), ev.x, ev.y)
    count, stamp = warped_event_images(ev, u, H, W)
    for b, w in enumerate(wins):
        for r, s in enumerate((0.0, 1.0)):
            C, A = ref_images(flow[b], w["x"], w["y"], taus(w), w["p"], s, H, W)
            np.testing.assert_allclose(count[b, r].numpy(), C, rtol=1e-12, atol=1e-12)
            np.testing.assert_allclose(stamp[b, r].numpy(), A, rtol=1e-12, atol=1e-12)


def test_forward_warp_flow_integer_shift_and_reference(backend):
    H, W = 5, 6
    flow = torch.zeros(1, 2, H, W, dtype=torch.float64)
    flow[:, 0], flow[:, 1] = 2.0, 1.0
    out = forward_warp_flow(flow)
    assert torch.all(out[:, 0, 1:, 2:] == 2.0) and torch.all(out[:, 1, 1:, 2:] == 1.0)
    assert torch.all(out[:, :, 0, :] == 0) and torch.all(out[:, :, :, :2] == 0)  # holes
    rng = np.random.default_rng(7)
    f = rng.normal(0, 1.5, (2, H, W))
    num = np.zeros((2, H, W))
    den = np.zeros((H, W))
    for r in range(H):
        for c in range(W):
            k = ref_kernel_image(c + f[0, r, c], r + f[1, r, c], H, W)
            den += k
            num += k[None] * f[:, r, c][:, None, None]
    want = np.where(den > 0, num / np.where(den > 0, den, 1), 0)
    got = forward_warp_flow(torch.from_numpy(f)[None])[0].numpy()
    np.testing.assert_allclose(got, want, rtol=1e-10, atol=1e-12)
    g = torch.from_numpy(rng.normal(0, 1.3, (1, 2, 4, 4))).requires_grad_()
    assert torch.autograd.gradcheck(forward_warp_flow, (g,))


@pytest.mark.parametrize("threads", [1, 2])
def test_forward_warp_flow_compiled_equals_torch_path(monkeypatch, threads):
    """The compiled kernel against the torch path: values and gradients, float32 and float64,
    a batch with flows that leave the image, land on integer pixels and pile onto one pixel,
    and its first image alone (a single image is splatted in row strips, summed afterwards)."""
    if warp._kernels is None:
        pytest.skip("numba not installed")
    gen = torch.Generator().manual_seed(3)
    flow = torch.randn(3, 2, 19, 26, generator=gen, dtype=torch.float64) * 4
    flow[0, :, :6] = torch.round(flow[0, :, :6])  # integer displacements
    flow[1, 0, :, :4] = -30.0  # out of the image
    flow[2] = 0.5  # a constant shift: every target pixel receives from up to four sources
    weights = torch.randn(3, 2, 19, 26, generator=gen, dtype=torch.float64)
    assert warp._kernels.warp_strips(1) > 1 and warp._kernels.warp_strips(3) == 1
    cases = [(dtype, tol, batch) for dtype, tol in ((torch.float64, 1e-12), (torch.float32, 1e-4)) for batch in (3, 1)]
    for dtype, tol, batch in cases:
        results = []
        for kernels in (warp._kernels, None):
            monkeypatch.setattr(warp, "_kernels", kernels)
            f = flow[:batch].detach().clone().to(dtype).requires_grad_()  # a fresh leaf per run: its own .grad
            before = torch.get_num_threads()
            torch.set_num_threads(threads)  # the serial or the parallel compiled kernels
            try:
                out = forward_warp_flow(f)
                (out * weights[:batch].to(dtype)).sum().backward()
            finally:
                torch.set_num_threads(before)
            results.append((out.detach(), f.grad))
        (out_c, grad_c), (out_t, grad_t) = results
        assert grad_c is not None and grad_t is not None and grad_c is not grad_t
        assert grad_c.abs().max() > 0.1  # the gradient comparison is not zero against zero
        torch.testing.assert_close(out_c, out_t, rtol=tol, atol=tol)
        torch.testing.assert_close(grad_c, grad_t, rtol=tol, atol=tol)


def _tiny_weight_collision(eps: float) -> torch.Tensor:
    """A 5x5 flow whose only sources reaching pixel (row 2, col 2) are (1, 1), moved by
    (eps, eps), and (4, 4), moved by (-1 - eps, -1 - eps): each leaves weight eps^2 there (the
    far corner of its splat), with flows a pixel apart. Every other pixel leaves the image."""
    flow = torch.full((1, 2, 5, 5), 40.0, dtype=torch.float64)
    flow[0, :, 1, 1] = eps
    flow[0, :, 4, 4] = -1.0 - eps
    return flow


@pytest.mark.parametrize("min_weight", [warp.HOLE_WEIGHT, 0.0])
def test_forward_warp_gradient_bounded_at_tiny_weight_collisions(backend, min_weight):
    """Eq. 9's backward divides by the target's splatted weight A0: with no threshold the
    gradient at a tiny-weight collision grows as 1 / eps; with HOLE_WEIGHT the pixel is a hole
    (as a zero-weight one is) and the gradient stays bounded however small eps gets."""
    largest = []
    for eps in (1e-3, 1e-4, 1e-6):
        flow = _tiny_weight_collision(eps).requires_grad_()
        out = forward_warp_flow(flow, min_weight=min_weight)
        a0 = 2 * eps**2  # the target's weight, written out
        assert a0 < warp.HOLE_WEIGHT
        if min_weight > 0:
            assert torch.all(out[0, :, 2, 2] == 0)  # a hole
        else:
            mean = (eps + (-1.0 - eps)) / 2  # two sources of equal weight: their mean
            assert out[0, 0, 2, 2].item() == pytest.approx(mean, rel=1e-6)
        out[0, 0, 2, 2].backward()
        largest.append(flow.grad.abs().max().item())
    if min_weight > 0:
        assert max(largest) == 0.0  # nothing else reaches the hole
    else:
        # d out / d u_x of a source = wy * (u_src - out) / A0 * d wx / dx ~ 1 / (2 eps)
        assert largest[0] > 100 and largest[2] > 1e5 and largest[2] > 500 * largest[0]


def test_forward_warp_threshold_leaves_ordinary_pixels(backend):
    """Above the threshold nothing changes: a smooth flow warps to the same field with
    min_weight = 0 and with HOLE_WEIGHT (every pixel's weight is far above it or exactly 0)."""
    rows, cols = torch.meshgrid(torch.arange(12.0), torch.arange(15.0), indexing="ij")
    flow = torch.stack([0.3 * torch.sin(rows / 3) + 1.7, 0.2 * cols / 5 - 0.6])[None].double()
    torch.testing.assert_close(forward_warp_flow(flow, min_weight=0.0), forward_warp_flow(flow), rtol=0, atol=0)
    with pytest.raises(ValueError, match="min_weight"):
        forward_warp_flow(flow, min_weight=-1.0)


def test_event_pixel_mask_rounds_and_ignores_padding(backend):
    x = torch.tensor([[0.0, 2.4, 2.6, -0.7, 3.0]])
    y = torch.tensor([[0.0, 1.0, 1.0, 0.0, 9.0]])
    m = torch.tensor([[True, True, True, True, False]])
    got = event_pixel_mask(x, y, m, 3, 4)
    want = torch.zeros(1, 3, 4, dtype=torch.bool)
    want[0, 0, 0] = want[0, 1, 2] = want[0, 1, 3] = True
    assert torch.equal(got, want)


# --------------------------------------------------------------------------------------------
# Gradients
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("integer", [True, False])
def test_gradcheck_hmc(integer, backend):
    rng = np.random.default_rng(11 + integer)
    H, W = 6, 7
    wins = [random_window(rng, 25, H, W, integer=integer), random_window(rng, 12, H, W)]
    ev = EventBatch.from_windows(wins, dtype=torch.float64)
    flow = torch.from_numpy(rng.normal(0, 1.2, (2, 2, H, W))).requires_grad_()
    assert torch.autograd.gradcheck(lambda f: hmc_loss(f, ev).loss, (flow,), eps=1e-6, atol=1e-5)
    coarse = torch.from_numpy(rng.normal(0, 1.2, (2, 2, 3, 4))).requires_grad_()
    assert torch.autograd.gradcheck(lambda a, b: hmc_loss([a, b], ev).loss, (coarse, flow),
                                    eps=1e-6, atol=1e-5)


def test_gradcheck_accumulated(backend):
    rng = np.random.default_rng(13)
    H, W = 5, 6
    evs = [EventBatch.from_windows([random_window(rng, 15, H, W, integer=False)], dtype=torch.float64)
           for _ in range(2)]
    flows = [torch.from_numpy(rng.normal(0, 1, (1, 2, H, W))).requires_grad_() for _ in range(2)]
    assert torch.autograd.gradcheck(lambda a, b: accumulated_hmc_loss([a, b], evs).loss,
                                    tuple(flows), eps=1e-6, atol=1e-5)


# --------------------------------------------------------------------------------------------
# Behaviour on an analytic translating pattern
# --------------------------------------------------------------------------------------------


def translating_dots(v=(12.0, 6.0), H=64, W=64, n_dots=14, per_dot=60, seed=0, dur=10_000):
    """Dots moving at constant velocity v (pixels per window); each emits events at its
    rounded position at evenly spaced times. Ground-truth flow: v everywhere."""
    rng = np.random.default_rng(seed)
    xs, ys, ts, ps = [], [], [], []
    for d in range(n_dots):
        x0, y0 = rng.uniform(14, 36), rng.uniform(8, 40)
        pol = 1 if d % 2 == 0 else -1
        t = np.sort(rng.integers(0, dur, per_dot))
        tau = t / dur
        xs.append(np.round(x0 + tau * v[0]))
        ys.append(np.round(y0 + tau * v[1]))
        ts.append(t)
        ps.append(np.full(per_dot, pol))
    order = np.argsort(np.concatenate(ts), kind="stable")
    cat = lambda a: np.concatenate(a)[order]  # noqa: E731
    return dict(x=cat(xs), y=cat(ys), t=cat(ts), p=cat(ps), t_start=0, t_end=dur), (H, W)


def test_ground_truth_flow_beats_wrong_flows_on_translating_pattern():
    v = (12.0, 6.0)
    w, (H, W) = translating_dots(v)
    ev = EventBatch.from_windows([w], dtype=torch.float64)

    def flow_of(scale):
        f = torch.zeros(1, 2, H, W, dtype=torch.float64)
        f[:, 0], f[:, 1] = v[0] * scale, v[1] * scale
        return f

    res = {s: hmc_loss(flow_of(s), ev) for s in (1.0, 0.0, 0.5, 2.0)}
    res_at = {s: at_loss(flow_of(s), ev) for s in (1.0, 0.0, 0.5, 2.0)}
    for wrong in (0.0, 0.5, 2.0):
        assert res[1.0].components["at"] < res[wrong].components["at"], wrong
        assert res[1.0].components["ec"] < res[wrong].components["ec"], wrong
        assert res[1.0].loss < res[wrong].loss, wrong
        assert res_at[1.0].loss < res_at[wrong].loss, wrong


def test_event_count_loss_zero_for_empty_window(backend):
    H, W = 8, 8
    empty = dict(x=np.zeros(0), y=np.zeros(0), t=np.zeros(0, np.int64), p=np.zeros(0),
                 t_start=0, t_end=100)
    ev = EventBatch.from_windows([empty, empty])
    out = hmc_loss(torch.randn(2, 2, H, W), ev)
    assert torch.all(out.components["ec"] == 0)
    assert torch.all(out.components["at"] == 0)
    assert torch.all(out.components["smooth"] == 0)
    assert torch.all(out.components["kept"] == 1)
    assert out.loss.item() == 0.0


@pytest.mark.parametrize("loss, fn", [("hmc", hmc_loss), ("at", at_loss)])
def test_window_loss_is_the_weighted_loss_plus_the_border_rule(loss, fn):
    """window_loss = the loss with the weights, plus border_penalty x each window's zero-flow loss
    x its charge; zero_flow_loss is window_loss of zero flow (the rule charges zero flow nothing);
    a zero-flow loss handed in is the one computed; a batch gives each window its loss alone."""
    a, (H, W) = translating_dots((12.0, 6.0))
    b, _ = translating_dots((-5.0, 3.0), per_dot=40, seed=1)  # fewer events: the batch pads it
    ev = EventBatch.from_windows([a, b], dtype=torch.float64)
    weights = LossWeights(lambda_1=0.8, lambda_2=0.01, alpha=0.5, border_penalty=0.7, border_ramp=4.0)
    flow = torch.randn(2, 2, H, W, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    flow[1] += 20.0  # the second window's events leave the frame
    zero = fn(torch.zeros_like(flow), ev, **weights.of(loss)).per_sample
    expected = fn(flow, ev, border_penalty=0.7 * zero, **weights.of(loss)).per_sample
    out = window_loss(flow, ev, weights, loss=loss)
    torch.testing.assert_close(out.per_sample, expected)
    assert out.per_sample[1] > fn(flow, ev, **weights.of(loss)).per_sample[1] + 0.1 * zero[1]  # the rule charged
    torch.testing.assert_close(zero_flow_loss(flow, ev, weights, loss=loss).per_sample, zero)
    torch.testing.assert_close(window_loss(torch.zeros_like(flow), ev, weights, loss=loss).per_sample, zero)
    torch.testing.assert_close(window_loss(flow, ev, weights, loss=loss, zero_flow=zero).per_sample, expected)
    for i, window in enumerate((a, b)):
        alone = window_loss(flow[i : i + 1], EventBatch.from_windows([window], dtype=torch.float64), weights, loss=loss)
        torch.testing.assert_close(alone.per_sample, expected[i : i + 1])
    with pytest.raises(ValueError, match=r"loss must be one of \('hmc', 'at'\), got 'l1'"):
        window_loss(flow, ev, loss="l1")


def test_kept_share_and_border_penalty_expose_the_border_hole(backend):
    w, (H, W) = translating_dots()
    ev = EventBatch.from_windows([w], dtype=torch.float64)
    away = torch.full((1, 2, H, W), 1e6, dtype=torch.float64)  # pushes (almost) all off-sensor
    zero = torch.zeros_like(away)
    out, out_zero = hmc_loss(away, ev), hmc_loss(zero, ev)
    # the hole: the paper's loss prefers throwing the events away
    assert out.loss.item() < out_zero.loss.item()
    assert out.components["kept"].item() < 0.01
    assert out_zero.components["kept"].item() == pytest.approx(1.0)
    pen = hmc_loss(away, ev, border_penalty=1.0, border_ramp=0.0)
    pen_zero = hmc_loss(zero, ev, border_penalty=1.0, border_ramp=0.0)
    assert pen.loss.item() > pen_zero.loss.item()
    assert pen_zero.loss.item() == pytest.approx(out_zero.loss.item())


def ref_ramped_charge(flow, x, y, tau, s, H, W, ramp):
    """Per event: the bilinear corners that land off the image (their weights summed) times
    min(1, d / ramp), d = L1 distance beyond the image; the mean over events (explicit loops)."""
    total = 0.0
    for xi, yi, ti in zip(x, y, tau):
        u = ref_sample(flow, xi, yi)
        xw, yw = xi + (s - ti) * u[0], yi + (s - ti) * u[1]
        x0, y0 = math.floor(xw), math.floor(yw)
        off = 0.0
        for cx, wx in ((x0, 1 - (xw - x0)), (x0 + 1, xw - x0)):
            for cy, wy in ((y0, 1 - (yw - y0)), (y0 + 1, yw - y0)):
                if not (0 <= cx < W and 0 <= cy < H):
                    off += wx * wy
        d = max(0.0, -xw) + max(0.0, xw - (W - 1)) + max(0.0, -yw) + max(0.0, yw - (H - 1))
        total += off * min(1.0, d / ramp)
    return total / max(len(x), 1)


@pytest.mark.parametrize("ramp", [0.5, 3.0, 16.0])
def test_border_ramp_matches_slow_reference(ramp, backend):
    rng = np.random.default_rng(21)
    H, W = 9, 12
    wins = [random_window(rng, 60, H, W, integer=False, border=True), random_window(rng, 40, H, W, integer=False),
            random_window(rng, 0, H, W)]
    ev = EventBatch.from_windows(wins, dtype=torch.float64)
    flow = torch.from_numpy(rng.normal(0, 4.0, (3, 2, H, W)))
    weight = torch.tensor([1.0, 2.5, 3.0], dtype=torch.float64)
    plain = hmc_loss(flow, ev)
    ramped = hmc_loss(flow, ev, border_penalty=weight, border_ramp=ramp)
    for b, w in enumerate(wins):
        fl = flow[b].numpy()
        charge = sum(ref_ramped_charge(fl, w["x"], w["y"], taus(w), s, H, W, ramp) for s in (0.0, 1.0))
        expected = plain.per_sample[b].item() + weight[b].item() * charge
        assert ramped.per_sample[b].item() == pytest.approx(expected, rel=RTOL, abs=1e-12)
    assert ramped.per_sample[2].item() == plain.per_sample[2].item()  # empty window: no charge
    # the ramp only ever lowers the charge, and a vanishing ramp is the plain dropped share
    full = hmc_loss(flow, ev, border_penalty=weight, border_ramp=0.0)
    assert (ramped.per_sample <= full.per_sample + 1e-12).all()
    tiny = hmc_loss(flow, ev, border_penalty=weight, border_ramp=1e-9)
    torch.testing.assert_close(tiny.per_sample, full.per_sample, rtol=1e-6, atol=1e-9)


def test_border_ramp_charges_near_motion_little_and_far_pushes_fully():
    H = W = 32
    w = random_window(np.random.default_rng(5), 200, H, W, integer=False, border=True)  # on the border columns
    ev = EventBatch.from_windows([w], dtype=torch.float64)
    zero = hmc_loss(torch.zeros(1, 2, H, W, dtype=torch.float64), ev).per_sample
    for v, share in ((1e6, 1.0), (3.0, None)):
        flow = torch.zeros(1, 2, H, W, dtype=torch.float64)
        flow[:, 0] = v
        plain = hmc_loss(flow, ev)
        full = hmc_loss(flow, ev, border_penalty=zero, border_ramp=0.0).loss - plain.loss
        ramped = hmc_loss(flow, ev, border_penalty=zero, border_ramp=16.0).loss - plain.loss
        if share:  # pushed 1e6 px out: the ramp changes nothing, the game costs 2 x zero flow's loss
            assert ramped.item() == pytest.approx(full.item(), rel=1e-4)
            assert hmc_loss(flow, ev, border_penalty=zero, border_ramp=16.0).loss > 1.9 * zero.item()
        else:  # 3 px across the border: at most 3/16 of the plain charge
            assert 0 < ramped.item() <= 3 / 16 * full.item()


def test_gradcheck_border_ramp():
    rng = np.random.default_rng(23)
    H, W = 6, 7
    ev = EventBatch.from_windows([random_window(rng, 30, H, W, integer=False, border=True)], dtype=torch.float64)
    flow = torch.from_numpy(rng.normal(0, 2.0, (1, 2, H, W))).requires_grad_()
    assert torch.autograd.gradcheck(lambda f: hmc_loss(f, ev, border_penalty=1.3, border_ramp=2.0).loss, (flow,),
                                    eps=1e-6, atol=1e-5)


def test_border_ramp_must_be_a_finite_non_negative_length():
    ev, flow = EventBatch.from_windows([random_window(np.random.default_rng(0), 5, 4, 4)]), torch.zeros(1, 2, 4, 4)
    for bad in (-1.0, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="border_ramp"):
            hmc_loss(flow, ev, border_penalty=1.0, border_ramp=bad)


# --------------------------------------------------------------------------------------------
# Bad input: clear errors, never silent garbage
# --------------------------------------------------------------------------------------------


def _small_batch(B=2, H=6, W=7, n=10):
    rng = np.random.default_rng(21)
    return EventBatch.from_windows([random_window(rng, n, H, W) for _ in range(B)]), (H, W)


@pytest.mark.parametrize("shape", [(2, 3, 6, 7), (2, 6, 7), (2, 2, 6, 7, 1)])
def test_bad_flow_shape(shape):
    ev, _ = _small_batch()
    with pytest.raises(ValueError, match=r"\(B, 2, H, W\)"):
        hmc_loss(torch.zeros(shape), ev)


def test_batch_size_mismatch():
    ev, (H, W) = _small_batch(B=2)
    with pytest.raises(ValueError, match="batch size mismatch"):
        hmc_loss(torch.zeros(3, 2, H, W), ev)
    with pytest.raises(ValueError, match="different batch sizes"):
        hmc_loss([torch.zeros(2, 2, H, W), torch.zeros(1, 2, 3, 3)], ev)


@pytest.mark.parametrize("bad", [float("nan"), float("inf"), -float("inf")])
def test_non_finite_flow(bad):
    ev, (H, W) = _small_batch()
    flow = torch.zeros(2, 2, H, W)
    flow[1, 0, 2, 3] = bad
    with pytest.raises(ValueError, match="NaN or inf"):
        hmc_loss(flow, ev)
    with pytest.raises(ValueError, match=r"flow\[1\] contains NaN or inf"):
        at_loss([torch.zeros(2, 2, 3, 3), flow], ev)


def test_time_outside_window():
    w = dict(x=np.array([1, 2]), y=np.array([1, 1]), t=np.array([10, 25]), p=np.array([1, -1]),
             t_start=10, t_end=20)
    ok = dict(w, t=np.array([10, 20]))  # t == t_end is accepted as tau = 1
    assert EventBatch.from_windows([ok]).tau[0, 1].item() == 1.0
    with pytest.raises(ValueError, match="window 1: event 1 has t = 25"):
        EventBatch.from_windows([ok, w])
    with pytest.raises(ValueError, match="outside"):
        EventBatch.from_windows([dict(w, t=np.array([9, 12]))])
    # an EventBatch built by hand with tau outside [0, 1] is refused by the loss
    ev = EventBatch.from_windows([ok])
    ev = ev._replace(tau=torch.tensor([[0.5, 1.5]]))
    with pytest.raises(ValueError, match=r"tau\[0, 1\] = 1.5"):
        hmc_loss(torch.zeros(1, 2, 4, 4), ev)
    # ... but padding slots may hold anything
    ev = ev._replace(mask=torch.tensor([[True, False]]))
    hmc_loss(torch.zeros(1, 2, 4, 4), ev)


def test_bad_event_fields_are_named():
    """tau outside [0, 1] or NaN, and NaN/inf coordinates, in a valid slot: a ValueError that
    names the field and the slot; tau is checked before the coordinates; padding slots may hold
    anything."""
    ev, (H, W) = _small_batch(B=2)
    flow = torch.zeros(2, 2, H, W)
    n = ev.x.shape[1]
    cases = [("tau", float("nan"), r"tau\[1, 2\] = nan"), ("tau", -0.25, r"tau\[1, 2\] = -0.25"),
             ("x", float("nan"), r"x or y at \[1, 2\] is NaN or inf"), ("y", float("inf"), r"x or y at \[1, 2\]")]
    for field, value, message in cases:
        bad = getattr(ev, field).clone()
        bad[1, 2] = value
        with pytest.raises(ValueError, match=message):
            hmc_loss(flow, ev._replace(**{field: bad}))
        padded = ev._replace(**{field: bad}, mask=ev.mask.clone().index_put_((torch.tensor([1]), torch.tensor([2])),
                                                                              torch.tensor(False)))
        hmc_loss(flow, padded)  # the same value in a padding slot is ignored
    both = ev._replace(x=ev.x.clone().index_fill_(1, torch.tensor([0]), float("nan")),
                       tau=ev.tau.clone().index_fill_(1, torch.tensor([n - 1]), 2.0))
    with pytest.raises(ValueError, match="tau"):
        hmc_loss(flow, both)


def test_empty_batch_and_other_malformed_input():
    with pytest.raises(ValueError, match="empty batch"):
        EventBatch.from_windows([])
    ev, (H, W) = _small_batch()
    with pytest.raises(ValueError, match="empty batch"):
        hmc_loss(torch.zeros(0, 2, H, W), ev)
    with pytest.raises(ValueError, match="empty list"):
        hmc_loss([], ev)
    with pytest.raises(ValueError, match="window 0: t_end"):
        EventBatch.from_windows([dict(x=[1], y=[1], t=[5], p=[1], t_start=5, t_end=5)])
    with pytest.raises(ValueError, match="different lengths"):
        EventBatch.from_windows([dict(x=[1, 2], y=[1], t=[5], p=[1], t_start=0, t_end=9)])
    with pytest.raises(ValueError, match="field 'p' has shape"):
        hmc_loss(torch.zeros(2, 2, H, W), ev._replace(p=ev.p[:, :3]))
    with pytest.raises(ValueError, match="K >= 1"):
        accumulated_hmc_loss([torch.zeros(2, 2, H, W)], [ev, ev])


def test_polarity_encodings_and_all_empty_batch(backend):
    base = dict(x=np.array([1, 2, 3]), y=np.array([1, 1, 2]), t=np.array([0, 5, 9]),
                t_start=0, t_end=10)
    a = EventBatch.from_windows([dict(base, p=np.array([1, 0, 1]))])
    b = EventBatch.from_windows([dict(base, p=np.array([True, False, True]))])
    c = EventBatch.from_windows([dict(base, p=np.array([1, -1, 1], np.int8))])
    assert torch.equal(a.p, b.p) and torch.equal(a.p, c.p)
    empty = dict(base, x=[], y=[], t=np.zeros(0, np.int64), p=[])
    ev = EventBatch.from_windows([empty, empty])
    assert ev.x.shape == (2, 0)
    flow = torch.randn(2, 2, 5, 5, requires_grad=True)
    out = hmc_loss(flow, ev)
    out.loss.backward()
    assert out.loss.item() == 0 and torch.all(flow.grad == 0)


# --------------------------------------------------------------------------------------------
# dtypes and devices
# --------------------------------------------------------------------------------------------


def test_float32_close_to_float64(backend):
    rng = np.random.default_rng(31)
    H, W = 20, 24
    wins = [random_window(rng, n, H, W, integer=False) for n in (200, 150)]
    flow = rng.normal(0, 3, (2, 2, H, W))
    l64 = hmc_loss(torch.from_numpy(flow), EventBatch.from_windows(wins, dtype=torch.float64))
    l32 = hmc_loss(torch.from_numpy(flow).float(), EventBatch.from_windows(wins))
    assert l32.loss.dtype == torch.float32
    # docs/method.md, "Conventions", numerics: L_AT may jump by ~1e-4 relative between precisions
    np.testing.assert_allclose(l32.per_sample.double().numpy(), l64.per_sample.numpy(), rtol=1e-3)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
def test_cuda_matches_cpu():
    rng = np.random.default_rng(41)
    H, W = 32, 40
    wins = [random_window(rng, n, H, W, integer=False) for n in (500, 0, 300)]
    flow = torch.from_numpy(rng.normal(0, 3, (3, 2, H, W)))
    cpu = hmc_loss(flow, EventBatch.from_windows(wins, dtype=torch.float64))
    fc = flow.cuda().requires_grad_()
    gpu = hmc_loss(fc, EventBatch.from_windows(wins, device="cuda", dtype=torch.float64))
    gpu.loss.backward()
    np.testing.assert_allclose(gpu.per_sample.cpu().detach().numpy(),
                               cpu.per_sample.detach().numpy(), rtol=1e-9)
    fcpu = flow.clone().requires_grad_()
    hmc_loss(fcpu, EventBatch.from_windows(wins, dtype=torch.float64)).loss.backward()
    np.testing.assert_allclose(fc.grad.cpu().numpy(), fcpu.grad.numpy(), rtol=1e-7, atol=1e-12)


def test_outside_distance_analytic_and_points_back_into_the_frame():
    from losses.warp import outside_distance

    x = torch.tensor([[0.0, 5.0, 9.0]])
    y = torch.tensor([[0.0, 2.0, 4.0]])
    t = torch.zeros(1, 3)
    mask = torch.tensor([[True, True, True]])
    u = torch.tensor([[[-3.0, 0.0], [0.0, 0.0], [2.0, 10.0]]], requires_grad=True)
    # s = 0: nothing moves; s = 1: 3 px left of x = 0, 1 px right of x = 10, 10 px below y = 4
    d = outside_distance(EventBatch(x, y, t, torch.ones_like(x), mask), u, 5, 11, (0.0, 1.0))
    assert float(d.detach()) == pytest.approx((3 + 1 + 10) / 3 / 2)
    d.sum().backward()
    assert u.grad[0, 0, 0] < 0 and u.grad[0, 2, 0] > 0 and u.grad[0, 2, 1] > 0  # descent moves them back
    assert u.grad[0, 1].abs().sum() == 0


def test_accumulated_loss_outside_weight_adds_the_distance_term():
    rng = np.random.default_rng(0)
    n, H, W = 50, 12, 16
    windows = [dict(x=rng.integers(0, W, n), y=rng.integers(0, H, n), t=np.sort(rng.integers(0, 1000, n)),
                    p=rng.integers(0, 2, n), t_start=0, t_end=1000) for _ in range(2)]
    batches = [EventBatch.from_windows([w]) for w in windows]
    flows = [torch.full((1, 2, H, W), 40.0) for _ in range(2)]  # pushes everything out
    plain = accumulated_hmc_loss(flows, batches)
    pulled = accumulated_hmc_loss(flows, batches, outside_weight=2.0)
    extra = float(pulled.loss - plain.loss)
    assert extra == pytest.approx(2.0 * float(pulled.components["outside_px"][0]) / W, rel=1e-5) and extra > 0


@pytest.mark.parametrize("scale", [0.5, 3.0, 40.0])  # sub-pixel, a few pixels, most events pushed out
def test_compiled_kernels_equal_torch_path(scale, monkeypatch):
    rng = np.random.default_rng(int(scale * 10))
    H, W = 23, 31
    wins = [random_window(rng, n, H, W, integer=i % 2 == 0, border=i == 1) for i, n in enumerate((300, 120, 0, 450))]
    flow = rng.normal(0, scale, (4, 2, H, W))
    results = {}
    for name in ("compiled", "torch"):
        if name == "torch":
            monkeypatch.setattr(image_terms, "_kernels", None)
            monkeypatch.setattr(smoothness, "_kernels", None)
        monkeypatch.setattr(warp, "_kernels", None)
        for dtype in (torch.float64, torch.float32):
            f = torch.from_numpy(flow).to(dtype).requires_grad_()
            out = hmc_loss(f, EventBatch.from_windows(wins, dtype=dtype), border_penalty=0.7, border_ramp=0.0)
            (out.per_sample * torch.arange(1, 5, dtype=dtype)).sum().backward()
            results[name, dtype] = (out.per_sample.detach().double(), out.components["kept"].double(), f.grad.double())
    for a, b in zip(results["compiled", torch.float64], results["torch", torch.float64]):
        np.testing.assert_allclose(a.numpy(), b.numpy(), rtol=1e-9, atol=1e-12)
    (l32, k32, g32), (l64, k64, g64) = results["compiled", torch.float32], results["compiled", torch.float64]
    np.testing.assert_allclose(l32.numpy(), l64.numpy(), rtol=1e-3)  # float32: docs/method.md, "Conventions", numerics
    np.testing.assert_allclose(k32.numpy(), k64.numpy(), rtol=1e-5)
    assert float((g32 - g64).norm() / g64.norm()) < 1e-2  # a few events sit on a kernel kink


def test_compiled_float32_exp_matches_exp():
    """The SIMD-friendly exp of the float32 kernels against float64 exp, over the range that
    -alpha C takes (C from 0 to far beyond any pixel count) and a little above 0."""
    import numba

    from losses import _kernels

    exp32 = numba.njit(lambda v: _kernels._exp(v))
    v = np.concatenate([np.linspace(-87.0, 2.0, 20001), [0.0, -0.6, -1e-8]]).astype(np.float32)
    got = np.array([exp32(np.float32(q)) for q in v], np.float64)
    want = np.exp(v.astype(np.float64))
    assert exp32(np.float32(0.0)) == 1.0  # an empty pixel contributes exactly 1 to S_P
    np.testing.assert_allclose(got, want, rtol=2e-7)
    assert exp32(1.5) == pytest.approx(np.exp(1.5), rel=1e-15)  # float64: the libm exp


def test_parallel_kernels_equal_serial_kernels():
    """The suite runs torch (and so the kernels) on one thread; users run the parallel kernels.
    Both give the same losses and gradients (float64), for several batch sizes, also when a
    batch has fewer tasks than threads, and twice in a row."""
    import numba

    if numba.config.NUMBA_NUM_THREADS < 2:
        pytest.skip("numba has a single thread here")
    rng = np.random.default_rng(5)
    H, W = 19, 26
    before = torch.get_num_threads()
    for B in (1, 3):
        wins = [random_window(rng, int(n), H, W, integer=b % 2 == 0, border=b == 1)
                for b, n in enumerate(rng.integers(50, 400, B))]
        ev = EventBatch.from_windows(wins, dtype=torch.float64)
        flow = torch.from_numpy(rng.normal(0, 2.5, (B, 2, H, W)))
        results = []
        try:
            for threads in (1, 2, 2):
                torch.set_num_threads(threads)
                f = flow.clone().requires_grad_()
                out = hmc_loss(f, ev, border_penalty=0.3, border_ramp=0.0)
                (out.per_sample * torch.arange(1, B + 1)).sum().backward()
                results.append((out.per_sample.detach(), f.grad))
        finally:
            torch.set_num_threads(before)
        for loss, grad in results[1:]:
            np.testing.assert_allclose(loss.numpy(), results[0][0].numpy(), rtol=1e-12)
            np.testing.assert_allclose(grad.numpy(), results[0][1].numpy(), rtol=1e-9, atol=1e-14)
