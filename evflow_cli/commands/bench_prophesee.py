"""Benchmark sections for Prophesee RAW reading and for ``predict`` (evflow_cli/predict.py).

``prophesee``: a synthetic 1280x720 (IMX636) recording of ``num_events`` uniformly random
events at ``rate`` events/s is encoded as EVT 3.0 and as EVT 2.0 (vectorised encoders below,
following the published word layouts; random events rarely share a row and a microsecond, so
the EVT 3.0 file holds single ADDR_X events and almost no vectors). A fresh child process opens
it through ``open_recording`` and reports:

- the first open, which decodes the whole file once to build the time index (events/s);
- a second open from the cached index (ms);
- a sequential read of every event, a million at a time (events/s);
- 10 ms windows read through ``events_between``, spread over the whole file (windows/s);
- the child's peak RSS growth while doing all that (the file's decoded events are far larger).

``predict``: ``evflow_cli.predict.predict`` end to end on CPU (windows, model, metrics, h5 writing;
no video) with the shipped default model, on synthetic-mini (64x64) and on a span of the
1280x720 EVT 3.0 file (33 ms windows).

``run(report, ...)`` is called by evflow_cli/commands/benchmark.py. Standalone:
``python scripts/bench_prophesee.py [--events N] [--sections prophesee predict]``.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from agents.options import command_parser, option, options_from_args, positive_float, positive_int
from evflow_cli.commands.bench_readers import peak_rss_mb, window_starts

SENSOR = (720, 1280)
DEFAULT_EVENTS = 20_000_000
DEFAULT_RATE = 2_000_000
WINDOW_US = 10_000


def _header(fmt: str) -> bytes:
    h, w = SENSOR
    version = "2.0" if fmt == "EVT2" else "3.0"
    return (f"% camera_integrator_name Prophesee\n% evt {version}\n% format {fmt};height={h};width={w}\n"
            f"% geometry {w}x{h}\n% end\n").encode()


def encode_evt2(x, y, t, p) -> np.ndarray:
    """(N,) sorted events -> uint32 words: a TIME_HIGH before each change of t >> 6."""
    high = t >> 6
    new_high = np.ones(len(t), bool)
    new_high[1:] = high[1:] != high[:-1]
    n_words = len(t) + int(new_high.sum())
    pos = np.arange(len(t)) + np.cumsum(new_high)  # each event's word, after its TIME_HIGH if any
    words = np.empty(n_words, np.uint32)
    words[pos[new_high] - 1] = (np.uint32(0x8) << 28) | (high[new_high] & 0x0FFFFFFF).astype(np.uint32)
    words[pos] = ((p.astype(np.uint32) << 28) | ((t & 63).astype(np.uint32) << 22)
                  | (x.astype(np.uint32) << 11) | y.astype(np.uint32))
    return words


def encode_evt3(x, y, t, p) -> np.ndarray:
    """(N,) sorted events -> uint16 words: TIME_HIGH / TIME_LOW / ADDR_Y when they change, then ADDR_X."""
    first = np.zeros(len(t), bool)
    first[0] = True
    change = lambda v: first | np.concatenate([[False], v[1:] != v[:-1]])  # noqa: E731
    new_high, new_low, new_y = change(t >> 12), change(t), change(y)
    new_low |= new_high
    new_y |= new_low  # keep the writer simple: y after every time change
    per_event = new_high.astype(np.int64) + new_low + new_y + 1
    end = np.cumsum(per_event)  # one past each event's ADDR_X word
    words = np.empty(int(end[-1]), np.uint16)
    ax = end - 1
    words[ax] = (0x2 << 12) | (p.astype(np.uint16) << 11) | x.astype(np.uint16)
    words[ax[new_y] - 1] = (0x0 << 12) | y[new_y].astype(np.uint16)
    low_at = ax - 1 - new_y
    words[low_at[new_low]] = (0x6 << 12) | (t[new_low] & 0xFFF).astype(np.uint16)
    words[low_at[new_high] - 1] = (0x8 << 12) | ((t[new_high] >> 12) & 0xFFF).astype(np.uint16)
    return words


def write_raw(path: Path, fmt: str, num_events: int, rate: float, chunk: int = 1 << 21, seed: int = 0) -> Path:
    """Stream a synthetic RAW file, ``chunk`` events at a time (bounded memory); each chunk
    restates the time base and row at its first event, which the formats allow."""
    rng = np.random.default_rng(seed)
    h, w = SENSOR
    span = chunk / rate * 1e6
    with open(path, "wb") as fh:
        fh.write(_header(fmt))
        for k, i0 in enumerate(range(0, num_events, chunk)):
            n = min(chunk, num_events - i0)
            t = np.sort(rng.integers(int(k * span), int(k * span + span * n / chunk), n)).astype(np.int64)
            x, y, p = rng.integers(0, w, n), rng.integers(0, h, n), rng.integers(0, 2, n)
            fh.write((encode_evt2 if fmt == "EVT2" else encode_evt3)(x, y, t, p).tobytes())
    return path


def _child(path: str, index_dir: str, max_windows: int) -> dict:
    from envs.readers import open_recording

    rss0 = peak_rss_mb()
    t0 = time.perf_counter()
    with open_recording(path, index_dir=index_dir) as reader:
        build_s = time.perf_counter() - t0
        n = reader.num_events
    t0 = time.perf_counter()
    with open_recording(path, index_dir=index_dir) as reader:
        cached_s = time.perf_counter() - t0
        t0 = time.perf_counter()
        for i in range(0, n, 1 << 20):
            reader.events_range(i, i + (1 << 20))
        sequential_s = time.perf_counter() - t0
        starts = window_starts(reader.t_start, reader.t_end, max_windows)
        reader._decoded.clear()
        t0 = time.perf_counter()
        events = sum(len(reader.events_between(int(s), int(s) + WINDOW_US)) for s in starts)
        windows_s = time.perf_counter() - t0
    return {"num_events": n, "build_s": build_s, "cached_ms": cached_s * 1e3, "sequential_s": sequential_s,
            "windows": len(starts), "window_events": events, "windows_s": windows_s,
            "rss_growth_mb": peak_rss_mb() - rss0}


def bench_reading(report, num_events: int, rate: float, max_windows: int, workdir: str | None) -> dict:
    results = {}
    with tempfile.TemporaryDirectory(dir=workdir, prefix="bench_prophesee-") as tmp:
        for fmt in ("EVT3", "EVT2"):
            path = write_raw(Path(tmp) / f"{fmt.lower()}.raw", fmt, num_events, rate)
            out = subprocess.run([sys.executable, "-m", "evflow_cli.commands.bench_prophesee", "--child", str(path), tmp, str(max_windows)],
                                 capture_output=True, text=True, check=False)
            if out.returncode != 0:
                raise RuntimeError(f"bench child for {fmt} failed:\n{out.stderr}")
            res = json.loads(out.stdout.strip().splitlines()[-1])
            label = f"{fmt} 1280x720 {num_events / 1e6:g}M ev ({path.stat().st_size / 2**20:.0f} MB)"
            report("prophesee", f"{label}: first open (index build)", res["num_events"] / res["build_s"] / 1e6, "Mev/s")
            report("prophesee", f"{label}: open from cached index", res["cached_ms"], "ms")
            report("prophesee", f"{label}: sequential read", res["num_events"] / res["sequential_s"] / 1e6, "Mev/s")
            report("prophesee", f"{label}: 10 ms windows", res["windows"] / res["windows_s"], "windows/s")
            report("prophesee", f"{label}: peak RSS growth", res["rss_growth_mb"], "MB")
            results[fmt] = res
            path.unlink()
    return results


def bench_predict(report, workdir: str | None, windows_full: int = 10, tiny: bool = False) -> None:
    """tiny: a fifth of synthetic-mini and 2 windows of a small RAW file (checks the section runs).

    At 1280x720 the levers of docs/performance.md, interleaved (each mode once per round, two
    rounds, the faster kept): the default's mode (network + finish), ``--coarse 2`` (the network on
    a 2x coarser grid), ``--no-finish`` and both; then the network alone in torch and, where
    onnxruntime is installed (not a dependency), the same network exported to ONNX and run by it."""
    from agents.pretrained import default_finish
    from agents.wrappers.coarse import CoarsePolicy
    from agents.wrappers.refine import FinishedPolicy, with_coarse
    from evflow_cli.predict import load_policy, predict

    policy, _ = load_policy(None, device="cpu")
    finishes = with_coarse(default_finish(), 1)
    modes = {
        "the default's mode": lambda: FinishedPolicy(policy, finishes),
        "--coarse 2": lambda: FinishedPolicy(policy, with_coarse(finishes, 2)),
        "--no-finish": lambda: policy,
        "--coarse 2 --no-finish": lambda: CoarsePolicy(policy, 2),
    }
    with tempfile.TemporaryDirectory(dir=workdir, prefix="bench_predict-") as tmp:
        predict(policy, "synthetic-mini", Path(tmp) / "warm.h5", end_s=0.2, progress=False)  # compile kernels
        res = predict(policy, "synthetic-mini", Path(tmp) / "mini.h5", progress=False, end_s=0.2 if tiny else None)
        report("predict", f"synthetic-mini 64x64, {res.windows} GT windows (CPU)", res.windows_per_second, "windows/s")
        windows_full = 2 if tiny else windows_full
        raw = write_raw(Path(tmp) / "cam.raw", "EVT3", 100_000 if tiny else 1_000_000, DEFAULT_RATE)
        options = dict(end_s=windows_full * 0.033334, progress=False, data_options={"index_dir": tmp}, overwrite=True,
                       score_windows=0)
        best: dict[str, float] = {}
        for _ in range(1 if tiny else 2):
            for mode, make in modes.items():
                res = predict(make(), raw, Path(tmp) / "cam.h5", **options)
                best[mode] = max(best.get(mode, 0.0), res.windows_per_second)
        for mode, rate in best.items():
            report("predict", f"EVT3 1280x720, {res.windows} windows of 33 ms, {mode}", rate, "windows/s")
        bench_network_runtimes(report, policy, (90, 160) if tiny else (720, 1280), rounds=1 if tiny else 3)


def bench_network_runtimes(report, policy, size: tuple[int, int], rounds: int = 3) -> None:
    """The default network's step on one ``size`` input (a second step: the recurrent state and
    the prior flow in use), torch against onnxruntime where installed, interleaved, the fastest
    of ``rounds`` each (evflow_cli/commands/bench_onnx.py exports the step)."""
    import torch

    from evflow_cli.commands.bench_onnx import NetworkStep

    step = NetworkStep(policy.model, size)
    timings: dict[str, float] = {}
    runners = {"torch": step.run_torch}
    try:
        runners["onnxruntime"] = step.onnxruntime_runner(threads=torch.get_num_threads())
    except ImportError:
        report("predict", "network at 1280x720, onnxruntime: not installed (pip install onnxruntime)", 0.0, "ms")
    for _ in range(rounds):
        for name, run in runners.items():
            began = time.perf_counter()
            run()
            timings[name] = min(timings.get(name, float("inf")), 1e3 * (time.perf_counter() - began))
    for name, ms in timings.items():
        report("predict", f"network step at {size[1]}x{size[0]}, {name}", ms, "ms")
    if "onnxruntime" in runners:
        report("predict", "  onnxruntime / torch flow, max abs difference", step.parity(), "px")


def run(report, num_events: int = DEFAULT_EVENTS, rate: float = DEFAULT_RATE, max_windows: int = 2000,
        sections=("prophesee", "predict"), workdir: str | None = None, tiny: bool = False) -> None:
    if "prophesee" in sections:
        bench_reading(report, num_events, rate, max_windows, workdir)
    if "predict" in sections:
        bench_predict(report, workdir, tiny=tiny)


def _print_row(section: str, row: str, value: float, unit: str) -> None:
    print(f"{section:<11} | {row:<60} | {value:12.3f} {unit}", flush=True)


@dataclass
class BenchPropheseeOptions:
    """How big a recording scripts/bench_prophesee.py writes, and which sections it times."""

    events: int = option(DEFAULT_EVENTS, type=positive_int)
    """events in the synthetic RAW file"""
    rate: float = option(DEFAULT_RATE, type=positive_float)
    """events per second"""
    max_windows: int = option(2000, type=positive_int)
    """windows read (spread evenly)"""
    sections: list[str] = option(default_factory=lambda: ["prophesee", "predict"], choices=["prophesee", "predict"])
    """prophesee: RAW reading at 1280x720; predict: evflow_cli/predict.py end to end"""
    workdir: str | None = None
    """where the synthetic file goes (default: system temp)"""


def build_parser() -> argparse.ArgumentParser:
    return command_parser(BenchPropheseeOptions, __doc__)


def main(argv=None) -> int:  # as bench_readers': "--child" measures one file in a fresh process
    argv = sys.argv[1:] if argv is None else argv
    if argv and argv[0] == "--child":
        print(json.dumps(_child(argv[1], argv[2], int(argv[3]))))
        return 0
    args = options_from_args(BenchPropheseeOptions, build_parser().parse_args(argv))
    run(_print_row, args.events, args.rate, args.max_windows, args.sections, args.workdir)
    return 0


if __name__ == "__main__":
    sys.exit(main())
