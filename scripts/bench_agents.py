"""Benchmark section for agents/: latency of one window through every model.

Rows, per width (paper c = 32, cpu c = 8) and input (256x256 batch 1, 128x128 batch 8):
forward latency per window (no grad, carrying the recurrent state) and forward + backward per
window (state from the previous window, detached; loss = mean of every scale's flow), in ms,
best of ``reps`` after one warm-up window; then EV-MGRFlowNet's latency as a ratio to
ConvGRU-EV-FlowNet's at the same width (target <= 1.3).

``run(report)`` is called by scripts/benchmark.py; ``report(section, row_name, value, unit)``
prints a row. Standalone: ``python scripts/bench_agents.py [--reps N] [--widths paper cpu]
[--device cpu|cuda]``.
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import torch

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from agents import make_model  # noqa: E402

SECTION = "agents"
MODELS = [  # (row label, registry name)
    ("EV-MGRFlowNet", "ev-mgrflownet"),
    ("ConvGRU-EV-FlowNet", "convgru-ev-flownet"),
    ("EV-FlowNet", "ev-flownet"),
    ("XLIF-EV-FlowNet", "xlif-ev-flownet"),
]
INPUTS = [("256x256 B=1", 1, 256, 256), ("128x128 B=8", 8, 128, 128)]


def _count_images(batch: int, height: int, width: int, seed: int) -> torch.Tensor:
    generator = torch.Generator().manual_seed(seed)
    counts = torch.randint(0, 4, (batch, 2, height, width), generator=generator).float()
    return counts * (torch.rand(batch, 1, height, width, generator=generator) < 0.3)


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def time_model(name: str, width: str, batch: int, height: int, size_w: int, reps: int, device) -> tuple[float, float]:
    """(forward ms, forward+backward ms) per window, best of ``reps`` after a warm-up window."""
    device = torch.device(device)
    torch.manual_seed(0)
    model = make_model(name, width=width).to(device)
    inputs = [_count_images(batch, height, size_w, seed).to(device) for seed in range(reps + 1)]

    forward_times = []
    with torch.no_grad():
        state = None
        for i, x in enumerate(inputs):
            _sync(device)
            start = time.perf_counter()
            _, state = model(x, state)
            _sync(device)
            if i > 0:  # the first window is the warm-up (and a fresh state)
                forward_times.append(time.perf_counter() - start)

    backward_times = []
    state = None
    for i, x in enumerate(inputs):
        model.zero_grad(set_to_none=True)
        _sync(device)
        start = time.perf_counter()
        flows, state = model(x, state)
        loss = sum(flow.mean() for flow in flows)
        loss.backward()
        _sync(device)
        if i > 0:
            backward_times.append(time.perf_counter() - start)
        state = {key: value.detach() for key, value in state.items()}
    return 1e3 * min(forward_times), 1e3 * min(backward_times)


def run(report, reps: int = 2, widths=("paper", "cpu"), device: str = "cpu") -> dict:
    """Report every row; return {(width, input, model label): (forward ms, fwd+bwd ms)}."""
    results = {}
    where = f"{device}, {torch.get_num_threads()} threads" if device == "cpu" else device
    for width in widths:
        for input_label, batch, height, size_w in INPUTS:
            for label, name in MODELS:
                fwd, fwd_bwd = time_model(name, width, batch, height, size_w, reps, device)
                results[(width, input_label, label)] = (fwd, fwd_bwd)
                row = f"{label} {width} {input_label} ({where})"
                report(SECTION, f"{row} forward", fwd, "ms/window")
                report(SECTION, f"{row} forward+backward", fwd_bwd, "ms/window")
            mgr = results[(width, input_label, "EV-MGRFlowNet")]
            base = results[(width, input_label, "ConvGRU-EV-FlowNet")]
            row = f"EV-MGRFlowNet / ConvGRU-EV-FlowNet {width} {input_label}"
            report(SECTION, f"{row} forward", mgr[0] / base[0], "x (target <= 1.3)")
            report(SECTION, f"{row} forward+backward", mgr[1] / base[1], "x")
    return results


def _print_row(section: str, row_name: str, value: float, unit: str) -> None:
    print(f"{section:8s} {row_name:70s} {value:10.2f} {unit}", flush=True)


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--reps", type=int, default=2, help="timed windows per row (best is reported)")
    parser.add_argument("--widths", nargs="+", default=["paper", "cpu"], choices=["paper", "cpu"])
    parser.add_argument("--device", default="cpu")
    args = parser.parse_args()
    run(_print_row, reps=args.reps, widths=args.widths, device=args.device)
