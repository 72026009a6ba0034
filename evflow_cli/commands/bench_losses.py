"""Benchmark section for losses/: forward + backward of L_HMC, in events per second.

Rows: the fast ``losses.hmc_loss`` and, as the comparison, a straightforward implementation in
the style of the TU Delft event_flow code (per-corner index tensors concatenated and repeated,
one scatter per image into a (B, H*W, 1) buffer), written here (:func:`straightforward_hmc_loss`:
the benchmark's yardstick, not a loss of the project: the paper's bare L_HMC on integer event
coordinates, no border rule and no ``losses.LossSpec``; the tests hold the losses to slow
references of their own), measured in the same run on the
same data (each the best of ``repeats`` calls, the two taking turns); the ratio of the best
times and the median over turns of the ratio within a turn (robust to bursts of load on a
shared machine); and the floor of one scatter-add + one gather of 4N floats.

``run(report)`` is called by evflow_cli/commands/benchmark.py; ``report(section, row_name, value, unit)``
prints a row. Standalone: ``python scripts/bench_losses.py [--quick]``.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from dataclasses import dataclass

import torch

from agents.options import DeviceOptions, command_parser, option, options_from_args, positive_int
from losses import EventBatch, LossSpec, hmc_loss

SECTION = "losses"
CONFIGS = [  # (name, batch, events per window, height, width)
    ("30k ev 256x256 B=8", 8, 30_000, 256, 256),
    ("100k ev 346x260 B=1", 1, 100_000, 260, 346),
]


def synthetic_batch(B, N, H, W, seed=0, device="cpu"):
    """Raw-sensor-like windows: integer pixels, sorted tau in [0, 1), random polarity; and a
    smooth random flow field (B, 2, H, W) of a few pixels per window."""
    g = torch.Generator().manual_seed(seed)
    x = torch.randint(0, W, (B, N), generator=g).float()
    y = torch.randint(0, H, (B, N), generator=g).float()
    tau = torch.sort(torch.rand(B, N, generator=g), dim=1).values
    p = torch.where(torch.rand(B, N, generator=g) > 0.5, 1.0, -1.0)
    ev = EventBatch(x, y, tau, p, torch.ones(B, N, dtype=torch.bool)).to(device)
    coarse = torch.randn(B, 2, 8, 8, generator=g) * 4
    flow = torch.nn.functional.interpolate(coarse, size=(H, W), mode="bilinear", align_corners=False)
    return ev, flow.to(device)


# ---------------------------------------------------------------------------------------------
# The straightforward implementation (event_flow style) the benchmark compares with; written
# for it alone.
# ---------------------------------------------------------------------------------------------


def _straightforward_corners(yx, H, W):
    """yx: (B, N, 2) warped (row, col). Returns idx (B, 4N, 1) long, weights (B, 4N, 1)."""
    top = torch.floor(yx[..., 0:1])
    left = torch.floor(yx[..., 1:2])
    tl = torch.cat([top, left], dim=2)
    tr = torch.cat([top, left + 1], dim=2)
    bl = torch.cat([top + 1, left], dim=2)
    br = torch.cat([top + 1, left + 1], dim=2)
    idx = torch.cat([tl, tr, bl, br], dim=1)  # (B, 4N, 2)
    rep = torch.cat([yx, yx, yx, yx], dim=1)
    zeros = torch.zeros_like(idx)
    w = torch.max(zeros, 1 - torch.abs(rep - idx))
    inside = (idx[..., 0:1] >= 0) & (idx[..., 0:1] < H) & (idx[..., 1:2] >= 0) & (idx[..., 1:2] < W)
    w = torch.prod(w, dim=2, keepdim=True) * inside
    flat = idx[..., 0:1] * W + idx[..., 1:2]
    flat = torch.where(inside, flat, torch.zeros_like(flat)).long()
    return flat, w


def _straightforward_scatter(flat, w, H, W):
    img = torch.zeros(flat.shape[0], H * W, 1, dtype=w.dtype, device=w.device)
    return img.scatter_add_(1, flat, w)


def straightforward_hmc_loss(flow, ev, lambda_1=LossSpec.lambda_1, lambda_2=LossSpec.lambda_2, alpha=LossSpec.alpha):
    """The paper's L_HMC (no border rule) the straightforward way, as the benchmark's comparison;
    integer event coordinates (flow gathered at the pixel)."""
    B, _, H, W = flow.shape
    flat_ev = (ev.y * W + ev.x).long()  # (B, N)
    u = torch.cat([torch.gather(flow[:, c].reshape(B, -1), 1, flat_ev).unsqueeze(2) for c in (1, 0)],
                  dim=2)  # (B, N, 2) as (dy, dx)
    yx = torch.stack([ev.y, ev.x], dim=2)
    tau = ev.tau.unsqueeze(2)
    m = ev.mask.unsqueeze(2).float()
    pos = (ev.p.unsqueeze(2) > 0).float() * m
    neg = (ev.p.unsqueeze(2) <= 0).float() * m
    pos4 = torch.cat([pos] * 4, dim=1)
    neg4 = torch.cat([neg] * 4, dim=1)
    total = 0.0
    for s in (0.0, 1.0):
        warped = yx + (s - tau) * u
        flat, w = _straightforward_corners(warped, H, W)
        ts = torch.cat([1 - torch.abs(s - tau)] * 4, dim=1)
        c_pos = _straightforward_scatter(flat, w * pos4, H, W)
        c_neg = _straightforward_scatter(flat, w * neg4, H, W)
        a_pos = _straightforward_scatter(flat, w * pos4 * ts, H, W)
        a_neg = _straightforward_scatter(flat, w * neg4 * ts, H, W)
        t_pos = a_pos / (c_pos + 1e-9)
        t_neg = a_neg / (c_neg + 1e-9)
        nnz = torch.sum((c_pos + c_neg) > 0, dim=(1, 2)).float()
        at = (torch.sum(t_pos**2, dim=(1, 2)) + torch.sum(t_neg**2, dim=(1, 2))) / (nnz + 1e-9)
        ec = (H * W / torch.sum(torch.exp(-alpha * c_pos), dim=(1, 2))
              + H * W / torch.sum(torch.exp(-alpha * c_neg), dim=(1, 2)) - 2)
        total = total + at + lambda_1 * ec
    # Charbonnier smoothness where both pixels have an input event
    has = torch.zeros(B, H * W, 1, device=flow.device)
    has = has.scatter_add_(1, flat_ev.unsqueeze(2), m).view(B, 1, H, W) > 0
    has = has.float()
    f = flow / max(H, W)
    smooth = 0.0
    for fa, fb, ma, mb in (
        (f[..., :, :-1], f[..., :, 1:], has[..., :, :-1], has[..., :, 1:]),
        (f[..., :-1, :], f[..., 1:, :], has[..., :-1, :], has[..., 1:, :]),
        (f[..., :-1, :-1], f[..., 1:, 1:], has[..., :-1, :-1], has[..., 1:, 1:]),
        (f[..., 1:, :-1], f[..., :-1, 1:], has[..., 1:, :-1], has[..., :-1, 1:]),
    ):
        smooth = smooth + torch.sum(torch.sqrt((fb - fa) ** 2 + 1e-6) * ma * mb, dim=(1, 2, 3))
    total = total + lambda_2 * smooth / 4
    return total.mean()


# ---------------------------------------------------------------------------------------------


def _time_interleaved(fns: dict, repeats: int) -> dict:
    """Every wall time of each function, {name: [seconds per repetition]}; the functions take
    turns within each repetition, so a busy shared machine slows them alike and the ratios of
    one repetition stay fair."""
    for fn in fns.values():
        fn()  # warm-up
    times = {name: [] for name in fns}
    for _ in range(repeats):
        for name, fn in fns.items():
            t0 = time.perf_counter()
            fn()
            times[name].append(time.perf_counter() - t0)
    return times


def run(report, quick: bool = False, device: str = "cpu", repeats: int | None = None,
        events_divisor: int | None = None) -> dict:
    """Measure every config; report rows in events/s and the fast/naive ratio. Returns the rows.
    events_divisor: fewer events per window (default 10 with ``quick``, else 1)."""
    results = {}
    repeats = repeats or (2 if quick else 10)
    divisor = events_divisor or (10 if quick else 1)
    for name, B, N, H, W in CONFIGS:
        N = max(1, N // divisor)
        ev, flow0 = synthetic_batch(B, N, H, W, device=device)
        n_events = B * N

        def fast():
            f = flow0.clone().requires_grad_()
            hmc_loss(f, ev).loss.backward()
            return f.grad

        def naive():
            f = flow0.clone().requires_grad_()
            straightforward_hmc_loss(f, ev).backward()
            return f.grad

        idx = torch.randint(0, B * H * W, (4 * n_events,), device=device)
        src = torch.rand(4 * n_events, device=device)

        def floor():
            buf = torch.zeros(B * H * W, device=device).index_add_(0, idx, src)
            return buf.index_select(0, idx)

        with torch.no_grad():  # the two implementations agree on the value
            diff = abs(hmc_loss(flow0, ev).loss.item() - straightforward_hmc_loss(flow0, ev).item())
        times = _time_interleaved({"fast": fast, "naive": naive, "floor": floor}, repeats)
        t = {key: min(values) for key, values in times.items()}
        per_turn = statistics.median(n / f for n, f in zip(times["naive"], times["fast"]))
        rows = {
            f"{name}: hmc_loss fwd+bwd": (n_events / t["fast"], "events/s"),
            f"{name}: straightforward fwd+bwd": (n_events / t["naive"], "events/s"),
            f"{name}: speed-up (best / best)": (t["naive"] / t["fast"], "x"),
            f"{name}: speed-up (median per turn)": (per_turn, "x"),
            f"{name}: floor (1 scatter + 1 gather of 4N)": (n_events / t["floor"], "events/s"),
            f"{name}: |fast - straightforward| loss": (diff, "abs"),
        }
        for row, (value, unit) in rows.items():
            report(SECTION, row, value, unit)
        results.update(rows)
    return results


def _print_row(section, row_name, value, unit):
    if unit == "events/s":
        text = f"{value / 1e6:10.3f} M events/s"
    elif unit == "x":
        text = f"{value:10.1f} x"
    else:
        text = f"{value:10.3g} {unit}"
    print(f"[{section}] {row_name:<55s} {text}", flush=True)


@dataclass
class BenchLossesOptions(DeviceOptions):
    """How big and how often scripts/bench_losses.py times the losses."""

    quick: bool = False
    """10x fewer events, fewer repeats"""
    repeats: int | None = option(None, type=positive_int)
    """timed repeats per row (default: the section's own)"""


def build_parser() -> argparse.ArgumentParser:
    return command_parser(BenchLossesOptions, __doc__)


def main(argv=None) -> int:
    args = options_from_args(BenchLossesOptions, build_parser().parse_args(argv))
    args.set_threads()
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads, device {args.device}")
    run(_print_row, quick=args.quick, device=args.device, repeats=args.repeats)
    return 0


if __name__ == "__main__":
    sys.exit(main())
