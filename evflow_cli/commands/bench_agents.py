"""Benchmark section for agents/: latency of one window through every model.

Rows, per width (paper c = 32, cpu c = 8) and input (256x256 batch 1, 128x128 batch 8):
forward latency per window (no grad, carrying the recurrent state) and forward + backward per
window (state from the previous window, detached; loss = mean of every scale's flow), in ms,
best of ``reps`` after one warm-up window; then EV-MGRFlowNet's latency as a ratio to
ConvGRU-EV-FlowNet's at the same width (target <= 1.3): the median over repetitions of the
ratio of the two models' times in that repetition (all models take turns in each repetition).
For reference, each width also reports the ratio of the two models' convolution and
matrix-product arithmetic (``evflow_cli.summary.forward_flops``), the part of the latency ratio that
no implementation removes, and, with ``--variants``, EV-MGRFlowNet's two ablations (what the
ST-ConvGRU and the prior-flow path each add) and, with ``--nchw``, every model in the NCHW
layout with torch's gate arithmetic (``model.channels_last = False``) and the speed-up of the
default layout over it. ``--parts`` instead times some of EV-MGRFlowNet's own pieces alone (the
forward warp of the prior flow and the ST-ConvGRU's pair update).

``run(report)`` is called by evflow_cli/commands/benchmark.py; ``report(section, row_name, value, unit)``
prints a row. Standalone: ``python scripts/bench_agents.py [--reps N] [--widths paper cpu]
[--variants] [--nchw] [--parts] [--device cpu|cuda] [--threads N]``.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from dataclasses import dataclass

import torch

from agents import WIDTHS, make_model
from agents.options import DeviceOptions, command_parser, option, options_from_args, positive_int
from evflow_cli.summary import forward_flops

SECTION = "agents"
MODELS = [  # (row label, registry name, keyword arguments)
    ("EV-MGRFlowNet", "ev-mgrflownet", {}),
    ("ConvGRU-EV-FlowNet", "convgru-ev-flownet", {}),
    ("EV-FlowNet", "ev-flownet", {}),
    ("XLIF-EV-FlowNet", "xlif-ev-flownet", {}),
]
VARIANTS = [
    ("EV-MGRFlowNet w/o ST-ConvGRU", "ev-mgrflownet", {"use_st_convgru": False}),
    ("EV-MGRFlowNet w/o prior flows", "ev-mgrflownet", {"use_prior_flow": False}),
]
NCHW = " (NCHW)"
WIDTHS_CPU = WIDTHS["cpu"]
INPUTS = [("256x256 B=1", 1, 256, 256), ("128x128 B=8", 8, 128, 128)]
TINY_INPUTS = [("32x32 B=1", 1, 32, 32)]  # benchmark.py --tiny: checks that the section runs


def _count_images(batch: int, height: int, width: int, seed: int, channels: int = 2) -> torch.Tensor:
    generator = torch.Generator().manual_seed(seed)
    counts = torch.randint(0, 4, (batch, channels, height, width), generator=generator).float()
    return counts * (torch.rand(batch, 1, height, width, generator=generator) < 0.3)


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def time_models(entries, width: str, batch: int, height: int, size_w: int, reps: int, device) -> dict:
    """{label: (forward ms, forward+backward ms, forward times s, forward+backward times s)} per
    window for ``entries`` [(label, registry name, kwargs, channels_last)]: the best of ``reps``
    after a warm-up window, and every repetition's time. The models take turns within each
    repetition, so load from other processes hits them alike and the ratios stay meaningful on
    a shared machine."""
    device = torch.device(device)
    models, states = {}, {}
    names = [label for label, _, _, _ in entries]
    for label, name, kwargs, channels_last in entries:
        torch.manual_seed(0)
        models[label] = make_model(name, width=width, **kwargs).to(device)
        models[label].channels_last = channels_last
    # EV-FlowNet reads 4 channels (counts and timestamps), the others the 2-channel count image
    channels = {label: getattr(model, "in_channels", 2) for label, model in models.items()}
    inputs = {c: [_count_images(batch, height, size_w, seed, c).to(device) for seed in range(reps + 1)]
              for c in set(channels.values())}
    forward = {name: [] for name in names}
    backward = {name: [] for name in names}

    with torch.no_grad():
        states = {name: None for name in names}
        for i in range(reps + 1):
            for name, model in models.items():
                x = inputs[channels[name]][i]
                _sync(device)
                start = time.perf_counter()
                _, states[name] = model(x, states[name])
                _sync(device)
                if i > 0:  # the first window is the warm-up (and a fresh state)
                    forward[name].append(time.perf_counter() - start)

    states = {name: None for name in names}
    for i in range(reps + 1):
        for name, model in models.items():
            x = inputs[channels[name]][i]
            model.zero_grad(set_to_none=True)
            _sync(device)
            start = time.perf_counter()
            flows, state = model(x, states[name])
            sum(flow.mean() for flow in flows).backward()
            _sync(device)
            if i > 0:
                backward[name].append(time.perf_counter() - start)
            states[name] = {key: value.detach() for key, value in state.items()}
    return {name: (1e3 * min(forward[name]), 1e3 * min(backward[name]), forward[name], backward[name])
            for name in names}


def turn_ratio(times: list[float], base: list[float]) -> float:
    """Median over repetitions of ``times[i] / base[i]``: the two models ran back to back in
    each repetition, so each ratio compares them under the same load, and the median drops the
    repetitions that a burst of load hit in between."""
    return statistics.median(a / b for a, b in zip(times, base))


def run(report, reps: int = 2, widths=("paper", "cpu"), device: str = "cpu", variants: bool = False,
        nchw: bool = False, inputs=None) -> dict:
    """Report every row; return {(width, input, model label): (forward ms, fwd+bwd ms)}.
    inputs: [(label, batch, height, width)] (default INPUTS)."""
    results = {}
    where = f"{device}, {torch.get_num_threads()} threads" if device == "cpu" else device
    entries = [(label, name, kwargs, None) for label, name, kwargs in MODELS + (VARIANTS if variants else [])]
    if nchw:
        entries += [(label + NCHW, name, kwargs, False) for label, name, kwargs, _ in entries]
    for width in widths:
        arithmetic = forward_flops(make_model("ev-mgrflownet", width=width), 1, 128, 128) / forward_flops(
            make_model("convgru-ev-flownet", width=width), 1, 128, 128
        )
        report(SECTION, f"EV-MGRFlowNet / ConvGRU-EV-FlowNet {width} arithmetic (GFLOP)", arithmetic, "x")
        for input_label, batch, height, size_w in inputs or INPUTS:
            timings = time_models(entries, width, batch, height, size_w, reps, device)
            for label, (fwd, fwd_bwd, _, _) in timings.items():
                results[(width, input_label, label)] = (fwd, fwd_bwd)
                row = f"{label} {width} {input_label} ({where})"
                report(SECTION, f"{row} forward", fwd, "ms/window")
                report(SECTION, f"{row} forward+backward", fwd_bwd, "ms/window")
            for suffix in ["", NCHW] if nchw else [""]:
                mgr = timings["EV-MGRFlowNet" + suffix]
                base = timings["ConvGRU-EV-FlowNet" + suffix]
                row = f"EV-MGRFlowNet / ConvGRU-EV-FlowNet{suffix} {width} {input_label}"
                target = "; target <= 1.3" if not suffix else ""
                report(SECTION, f"{row} forward", turn_ratio(mgr[2], base[2]), f"x (median per turn{target})")
                report(SECTION, f"{row} forward+backward", turn_ratio(mgr[3], base[3]), "x (median per turn)")
            if nchw:
                for label, _, _, layout in entries:
                    if layout is None:
                        ref, new = timings[label + NCHW], timings[label]
                        row = f"{label} {width} {input_label} NCHW / default layout"
                        report(SECTION, f"{row} forward", turn_ratio(ref[2], new[2]), "x (median per turn)")
                        report(SECTION, f"{row} forward+backward", turn_ratio(ref[3], new[3]), "x (median per turn)")
    return results


def _best_ms(fn, reps: int) -> float:
    fn()  # warm-up (and the kernels' compile on a new machine)
    times = []
    for _ in range(reps):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return 1e3 * min(times)


def time_parts(report, reps: int = 20) -> None:
    """``--parts``: EV-MGRFlowNet's own pieces at CPU width on CPU, at both inputs: the forward
    warp of the prior flow (eq. 9; flows ~ N(0, 3^2) pixels) forward and forward+backward, and
    the ST-ConvGRU's pair update (eq. 5, both GRUs from the 16 -> 96 input projection) forward."""
    from agents.layers import _GRUUpdates, use_gate_kernels
    from losses import forward_warp_flow

    generator = torch.Generator().manual_seed(0)
    for input_label, batch, height, width in INPUTS:
        flow = 3 * torch.randn(batch, 2, height, width, generator=generator)
        leaf = flow.clone().requires_grad_()

        def warp_both():
            forward_warp_flow(leaf).sum().backward()

        with torch.no_grad():
            report(SECTION, f"forward warp {input_label} forward", _best_ms(lambda: forward_warp_flow(flow), reps), "ms")
        report(SECTION, f"forward warp {input_label} forward+backward", _best_ms(warp_both, reps), "ms")
        channels = 2 * WIDTHS_CPU
        size = (batch, channels, height // 2, width // 2)
        layout = torch.channels_last
        projections = torch.randn(size[0], 6 * channels, *size[2:], generator=generator).contiguous(memory_format=layout)
        hidden = [torch.randn(*size, generator=generator).contiguous(memory_format=layout) for _ in range(2)]
        if not use_gate_kernels(projections):
            continue
        h_proj = [torch.randn(size[0], 3 * channels, *size[2:], generator=generator).contiguous(memory_format=layout)
                  for _ in range(2)]
        with torch.no_grad():
            report(SECTION, f"ST-ConvGRU pair update (compiled, convolutions apart) {input_label} forward",
                   _best_ms(lambda: _GRUUpdates.apply(channels, (0, 3 * channels), projections, h_proj[0], hidden[0], h_proj[1], hidden[1]), reps),
                   "ms")


def _print_row(section: str, row_name: str, value: float, unit: str) -> None:
    print(f"{section:8s} {row_name:70s} {value:10.2f} {unit}", flush=True)


@dataclass
class BenchAgentsOptions(DeviceOptions):
    """Which networks scripts/bench_agents.py times, and how often."""

    reps: int = option(2, type=positive_int)
    """timed windows per row (best is reported)"""
    widths: list[str] = option(default_factory=lambda: ["paper", "cpu"], choices=sorted(WIDTHS))
    """the named widths timed"""
    variants: bool = False
    """also EV-MGRFlowNet's two ablations"""
    nchw: bool = False
    """also every model in NCHW with torch's gate arithmetic"""
    parts: bool = False
    """only EV-MGRFlowNet's own pieces, timed alone (forward warp, ST-ConvGRU pair update)"""


def build_parser() -> argparse.ArgumentParser:
    return command_parser(BenchAgentsOptions, __doc__)


def main(argv=None) -> int:
    args = options_from_args(BenchAgentsOptions, build_parser().parse_args(argv))
    args.set_threads()
    if args.parts:
        time_parts(_print_row, reps=max(args.reps, 20))
        return 0
    run(_print_row, reps=args.reps, widths=args.widths, device=args.device, variants=args.variants, nchw=args.nchw)
    return 0


if __name__ == "__main__":
    sys.exit(main())
