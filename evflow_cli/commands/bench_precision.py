"""Benchmark section "precision": does bfloat16 autocast (``--amp bf16``) speed up EV-MGRFlowNet?

An interleaved A/B in one process: each pair runs the float32 and the bf16 version back to back
(alternating which goes first), and a row is the median over the pairs of the per-pair time
ratio float32 / bf16 (above 1: bf16 is faster), with the quartiles beside it, so load from other
processes on a shared machine slows both sides of a pair alike. Rows, for EV-MGRFlowNet at CPU
width (c = 8) on a 96x96 crop, batch 8:

- forward: one window, no grad, the recurrent state carried;
- forward+backward: one window from a carried (detached) state, loss = mean squared flow of
  every scale, backward;
- training update: ``Learner.update`` (4 windows per update, L_HMC in float32) with ``amp`` off
  against bf16, two learners on the same recordings;
- bf16's rounding: the relative difference of the finest flow to float32's, same weights and input.

``run(report)`` is called by evflow_cli/commands/benchmark.py (``--only precision``); standalone:
``python -m evflow_cli.commands.bench_precision [--pairs N] [--device cpu|cuda] [--threads N]``.
The CPU's bf16 instructions (avx512_bf16, amx_bf16) are printed first: without them bf16 is emulated.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from agents import make_model
from agents.options import DeviceOptions, command_parser, option, options_from_args, positive_int

SECTION = "precision"


def cpu_bf16_flags() -> str:
    """The bf16 instruction sets /proc/cpuinfo lists ('none' when it lists none or is absent)."""
    try:
        words = set(Path("/proc/cpuinfo").read_text().split())
    except OSError:
        return "unknown"
    return " ".join(flag for flag in ("avx512_bf16", "amx_bf16", "amx_tile") if flag in words) or "none"


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def _pairs(fp32, bf16, pairs: int, device: torch.device) -> list[float]:
    """Per-pair time ratios fp32 / bf16 of the two callables, alternating which runs first."""
    fp32(), bf16()  # warm-up (oneDNN picks its kernels at the first call of each shape and dtype)
    ratios = []
    for k in range(pairs):
        times = {}
        for name, fn in ((("fp32", fp32), ("bf16", bf16)) if k % 2 == 0 else (("bf16", bf16), ("fp32", fp32))):
            _sync(device)
            start = time.perf_counter()
            fn()
            _sync(device)
            times[name] = time.perf_counter() - start
        ratios.append(times["fp32"] / times["bf16"])
    return ratios


def _report_ratios(report, row: str, ratios: list[float]) -> None:
    q1, median, q3 = statistics.quantiles(ratios, n=4) if len(ratios) > 1 else (ratios[0],) * 3
    report(SECTION, f"{row}: fp32 / bf16 time, median of {len(ratios)} pairs", median, "x")
    report(SECTION, f"{row}: fp32 / bf16 time, quartile 1", q1, "x")
    report(SECTION, f"{row}: fp32 / bf16 time, quartile 3", q3, "x")


def network_rows(report, *, pairs: int, device: torch.device, batch: int, size: int) -> None:
    torch.manual_seed(0)
    model = make_model("ev-mgrflownet", width="cpu").to(device)
    generator = torch.Generator().manual_seed(0)
    x = (torch.randint(0, 4, (batch, 2, size, size), generator=generator).float()
         * (torch.rand(batch, 1, size, size, generator=generator) < 0.3)).to(device)
    with torch.no_grad():
        _, state = model(x, None)  # a carried state, as in a rollout

    def forward(dtype):
        def run():
            with torch.no_grad(), torch.autocast(device.type, dtype=dtype, enabled=dtype is not None):
                return model(x, state)[0]
        return run

    def forward_backward(dtype):
        def run():
            model.zero_grad(set_to_none=True)
            with torch.autocast(device.type, dtype=dtype, enabled=dtype is not None):
                flows, _ = model(x, state)
            sum(flow.float().square().mean() for flow in flows).backward()
        return run

    label = f"EV-MGRFlowNet cpu width {size}x{size} B={batch} ({device.type})"
    _report_ratios(report, f"{label} forward", _pairs(forward(None), forward(torch.bfloat16), pairs, device))
    _report_ratios(report, f"{label} forward+backward",
                   _pairs(forward_backward(None), forward_backward(torch.bfloat16), pairs, device))
    fp32, bf16 = forward(None)()[-1].float(), forward(torch.bfloat16)()[-1].float()
    report(SECTION, f"{label} bf16 finest flow vs fp32: |difference| / |fp32|",
           float((bf16 - fp32).norm() / fp32.norm().clamp_min(1e-12)), "")


def update_rows(report, *, pairs: int, device: torch.device, batch: int, size: int, unroll: int) -> None:
    from agents.learner import Learner
    from agents.train_config import TrainConfig
    from envs.recordings import write_translating_recording

    with tempfile.TemporaryDirectory() as tmp:
        sensor = size + size // 3
        data = [str(write_translating_recording(Path(tmp) / f"r{i}.h5", np.random.default_rng(i), sensor_size=(sensor, sensor),
                                                 duration_us=1_000_000, events_per_s=300_000)) for i in range(2)]
        learners = {amp: Learner(TrainConfig(data=data, crop=(size, size), num_envs=batch, unroll=unroll, flips=False,
                                             device=str(device), amp=amp)) for amp in ("off", "bf16")}
        try:
            ratios = _pairs(learners["off"].update, learners["bf16"].update, pairs, device)
        finally:
            for learner in learners.values():
                learner.close()
    _report_ratios(report, f"training update L={unroll} {size}x{size} crop B={batch} ({device.type})", ratios)


def run(report, pairs: int = 30, update_pairs: int = 8, device: str = "cpu", tiny: bool = False) -> None:
    """Every row (module docstring); ``tiny``: 2 pairs at 32x32, batch 2 (checks the section runs)."""
    device = torch.device(device)
    if device.type == "cpu":
        print(f"# {SECTION}: CPU bf16 instructions: {cpu_bf16_flags()}; {torch.get_num_threads()} torch threads", flush=True)
    batch, size, unroll = (2, 32, 2) if tiny else (8, 96, 4)
    network_rows(report, pairs=2 if tiny else pairs, device=device, batch=batch, size=size)
    update_rows(report, pairs=2 if tiny else update_pairs, device=device, batch=batch, size=size, unroll=unroll)


def _print_row(section: str, row: str, value: float, unit: str) -> None:
    print(f"{section:<11} | {row:<75} | {value:10.3f} {unit}", flush=True)


@dataclass
class BenchPrecisionOptions(DeviceOptions):
    """How many A/B pairs scripts/bench_precision.py times."""

    pairs: int = option(30, type=positive_int)
    """A/B pairs of the network rows"""
    update_pairs: int = option(8, type=positive_int)
    """A/B pairs of the training-update row"""


def build_parser() -> argparse.ArgumentParser:
    return command_parser(BenchPrecisionOptions, __doc__)


def main(argv=None) -> int:
    args = options_from_args(BenchPrecisionOptions, build_parser().parse_args(argv))
    args.set_threads()
    run(_print_row, pairs=args.pairs, update_pairs=args.update_pairs, device=args.device)
    return 0


if __name__ == "__main__":
    sys.exit(main())
