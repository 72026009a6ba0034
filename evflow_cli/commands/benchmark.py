"""Speed benchmarks, one section per part of the project. Prints `section | row | value unit`.

  python scripts/benchmark.py                      # every section
  python scripts/benchmark.py --only foundation env
  python scripts/benchmark.py --quick              # fewer repetitions
  python scripts/benchmark.py --only training precision --device cuda   # on a GPU
  python scripts/benchmark.py --only update --threads 1 --quick          # where a training update's time goes (CPU)
  python scripts/benchmark.py --tiny               # every section at the smallest sizes (a check, not a measurement)

Sections: foundation (project h5 windows + count images), simulator (with synthetic-dr-train
generation per sensor size), losses, agents, env, training (windows/s per model; on CPU also
2-process torchrun rows), precision (bf16 autocast against float32, interleaved A/B:
evflow_cli/commands/bench_precision.py), update (a profile of one training update at a campaign's
settings and interleaved A/B of ways to make it cheaper: evflow_cli/commands/bench_update.py),
readers, prophesee (RAW reading at 1280x720), predict (evflow_cli/predict.py end to end), tradeoff
(AEE and ms per window: the network, the network finished by a short solve, --cmax at two
budgets, on the same windows; the whole measurement: scripts/tradeoff.py). Timings
are wall-clock on whatever machine runs them; compare rows of one run. --device applies to the
losses, agents, training and precision sections.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from agents.options import DeviceOptions, command_parser, option, options_from_args

#: the repository (scripts/, tests/ for the recordings the training rows write)
ROOT = Path(__file__).resolve().parents[2]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

SECTIONS = ("foundation", "simulator", "losses", "agents", "env", "training", "precision", "update", "readers",
            "prophesee", "predict", "tradeoff", "window-memory")


def report(section: str, row: str, value: float, unit: str) -> None:
    print(f"{section:<11} | {row:<60} | {value:12.3f} {unit}", flush=True)


def _recording(path: Path, seconds: float = 4.0, rate: float = 2e6, size=(260, 346)):
    """A 346x260 recording at `rate` events/s (uniform random events)."""
    from envs.events import Events
    from envs.readers import H5Writer

    rng = np.random.default_rng(0)
    h, w = size
    with H5Writer(path, size, name="bench") as writer:
        chunk_s = 0.5
        for k in range(int(seconds / chunk_s)):
            n = int(rate * chunk_s)
            t = np.sort(rng.integers(int(k * chunk_s * 1e6), int((k + 1) * chunk_s * 1e6), n))
            writer.append_events(Events.create(rng.integers(0, w, n), rng.integers(0, h, n), t, rng.integers(0, 2, n), size))
    return path


def bench_foundation(quick: bool, tiny: bool = False) -> None:
    from envs.readers import H5Reader
    from envs.representations import count_image
    from envs.windows import iter_windows

    with tempfile.TemporaryDirectory() as tmp:
        seconds, rate = (0.5, 1e5) if tiny else (2.0 if quick else 4.0, 2e6)
        path = _recording(Path(tmp) / "rec.h5", seconds=seconds, rate=rate)
        with H5Reader(path) as reader:
            for mode, size, label in (("time", 10_000, "10 ms"), ("count", 30_000, "30k-event")):
                start = time.perf_counter()
                n = 0
                for window in iter_windows(reader, mode, size):
                    count_image(window.events)
                    n += 1
                elapsed = time.perf_counter() - start
                report("foundation", f"project h5 346x260 @2 Mev/s: {label} windows + count image", n / elapsed, "windows/s")


def bench_env(quick: bool, tiny: bool = False) -> None:
    import gymnasium

    import envs  # noqa: F401  (registers the ids)
    from envs.env import EventFlowEnv

    steps = 4 if tiny else 20 if quick else 60
    with tempfile.TemporaryDirectory() as tmp:
        path = str(_recording(Path(tmp) / "rec.h5", seconds=0.5 if tiny else 2.0, rate=1e5 if tiny else 1e6))
        for reward in (False, True):
            env = EventFlowEnv(path, window="time", window_size=10_000, compute_reward=reward)
            env.reset(seed=0)
            zero = np.zeros(env.action_space.shape, np.float32)
            start = time.perf_counter()
            for _ in range(steps):
                *_, truncated, _ = env.step(zero)
                if truncated:
                    env.reset()
            report("env", f"single env, 10 ms windows 346x260 @1 Mev/s, reward={'on' if reward else 'off'}", steps / (time.perf_counter() - start), "steps/s")
        for mode in ("sync", "async"):
            for reward in (False, True):
                vec = gymnasium.make_vec("EventFlow-v0", num_envs=4, vectorization_mode=mode, data=path, window="time",
                                         window_size=10_000, compute_reward=reward)
                vec.reset(seed=0)
                zero = np.zeros((4,) + vec.single_action_space.shape, np.float32)
                start = time.perf_counter()
                for _ in range(steps // 2):
                    vec.step(zero)
                rate = 4 * (steps // 2) / (time.perf_counter() - start)
                vec.close()
                report("env", f"make_vec 4 envs {mode}, reward={'on' if reward else 'off'}", rate, "env-steps/s")


def bench_training(quick: bool, tiny: bool = False, device: str = "cpu") -> None:
    """Training windows/s (rollout + loss + backward + step) at 128x128, batch 8, L = 10. On CPU:
    every model at CPU width, and EV-MGRFlowNet under torchrun with 1 and 2 processes (8 envs in
    all). On CUDA: EV-MGRFlowNet at CPU and paper width, float32 and bf16 autocast (one GPU: no
    torchrun rows, NCCL needs a GPU per process)."""
    import json
    import os
    import subprocess

    from agents.learner import Learner
    from agents.train_config import TrainConfig
    from envs.recordings import write_translating_recording

    steps = 1 if tiny else 2 if quick else 4
    size, batch, unroll = (32, 2, 2) if tiny else (128, 8, 10)
    cuda = torch.device(device).type == "cuda"
    if cuda:
        rows = [("ev-mgrflownet", width, amp) for width in ("cpu", "paper") for amp in ("off", "bf16")]
    else:
        rows = [(model, "cpu", "off") for model in ("ev-mgrflownet", "convgru-ev-flownet", "ev-flownet", "xlif-ev-flownet")]
    with tempfile.TemporaryDirectory() as tmp:
        data = [str(write_translating_recording(Path(tmp) / f"r{i}.h5", np.random.default_rng(i), sensor_size=(size, size),
                                                 duration_us=300_000 if tiny else 2_000_000,
                                                 events_per_s=50_000 if tiny else 400_000)) for i in range(2)]
        for model, width, amp in rows:
            learner = Learner(TrainConfig(model=model, data=data, num_envs=batch, unroll=unroll, width=width, flips=False,
                                          device=device, amp=amp))
            learner.update()  # warm-up (and the kernels' compile on a new machine)
            start = time.perf_counter()
            for _ in range(steps):
                learner.update()  # ends in float(loss): the device has finished the step
            precision = "" if amp == "off" else f", amp {amp}"
            report("training", f"{model} {width} width {size}x{size} B={batch} L={unroll} ({device}{precision})",
                   batch * unroll * steps / (time.perf_counter() - start), "windows/s")
            learner.close()
        if cuda:
            return
        for nproc in (1, 2):
            out = Path(tmp) / f"ddp{nproc}"
            cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", f"--nproc_per_node={nproc}",
                   "-m", "evflow_cli.commands.train", "--data", *data, "--num-envs", str(max(1, batch // nproc)),
                   "--unroll", str(unroll), "--steps", str(steps + 1), "--out", str(out), "--val-data", "",
                   "--no-progress", "--no-flips", "--device", "cpu"]
            env = {**os.environ, "OMP_NUM_THREADS": str(max(1, 2 // nproc)), "PYTHONPATH": str(ROOT)}
            done = subprocess.run(cmd, capture_output=True, text=True, env=env)
            if done.returncode != 0:
                raise RuntimeError(f"torchrun with {nproc} process(es) failed:\n{done.stderr[-3000:]}")
            rows = [json.loads(line) for line in (out / "metrics.jsonl").read_text().splitlines()]
            rate = rows[-1]["windows_per_s"] * nproc  # rank 0 logs its own windows; ranks roll equal shares
            report("training", f"ev-mgrflownet {size}x{size}, {batch} envs in all, torchrun {nproc} process(es)", rate,
                   "windows/s")


@dataclass
class BenchmarkOptions(DeviceOptions):
    """Which sections scripts/benchmark.py times, and how hard (--device: the losses, agents,
    training and precision sections)."""

    only: list[str] = option(default_factory=lambda: list(SECTIONS), choices=SECTIONS)
    """the sections to time"""
    quick: bool = False
    """fewer repetitions and smaller inputs"""
    tiny: bool = False
    """the smallest sizes and one repetition: checks that every section runs (the numbers mean nothing)"""


def build_parser() -> argparse.ArgumentParser:
    return command_parser(BenchmarkOptions, __doc__)


def main(argv=None) -> int:
    args = options_from_args(BenchmarkOptions, build_parser().parse_args(argv))
    args.set_threads()
    quick, tiny = args.quick or args.tiny, args.tiny
    print(f"# torch {torch.__version__}, {torch.get_num_threads()} threads, device {args.device}", flush=True)
    for section in args.only:
        if section == "foundation":
            bench_foundation(quick, tiny)
        elif section == "env":
            bench_env(quick, tiny)
        elif section == "training":
            bench_training(quick, tiny, args.device)
        elif section == "precision":
            from evflow_cli.commands import bench_precision

            bench_precision.run(report, device=args.device, tiny=tiny)
        elif section == "update":
            from evflow_cli.commands import bench_update

            bench_update.run(report, quick=quick, tiny=tiny)
        elif section == "simulator":
            from evflow_cli.commands import bench_simulator

            bench_simulator.run(report, quick=quick, tiny=tiny)
        elif section == "losses":
            from evflow_cli.commands import bench_losses

            bench_losses.run(report, quick=quick, device=args.device, repeats=1 if tiny else None,
                             events_divisor=1000 if tiny else None)
        elif section == "agents":
            from evflow_cli.commands import bench_agents

            bench_agents.run(report, reps=1 if quick else 2, device=args.device,
                             widths=("cpu",) if tiny else ("paper", "cpu"), inputs=bench_agents.TINY_INPUTS if tiny else None)
        elif section == "readers":
            from evflow_cli.commands import bench_readers

            if tiny:
                bench_readers.run(report, num_events=20_000, max_windows=10)
            else:
                bench_readers.run(report)
        elif section in ("prophesee", "predict"):
            from evflow_cli.commands import bench_prophesee

            events = 50_000 if tiny else 4_000_000 if quick else bench_prophesee.DEFAULT_EVENTS
            bench_prophesee.run(report, num_events=events, max_windows=10 if tiny else 2000, sections=(section,),
                                tiny=tiny)
        elif section == "tradeoff":
            bench_tradeoff(quick, tiny, args.device)
        elif section == "window-memory":
            bench_window_memory(quick, tiny)
    return 0


_WINDOW_MEMORY = """
import resource, sys
import numpy as np
from envs.env import EventFlowEnv
n, reward = int(sys.argv[1]), sys.argv[2] == "1"
rng = np.random.default_rng(0)
ev = np.zeros(n + 1, dtype=[("x", "<u2"), ("y", "<u2"), ("t", "<i8"), ("p", "i1")])
ev["x"], ev["y"], ev["p"] = rng.integers(0, 346, n + 1), rng.integers(0, 260, n + 1), rng.integers(0, 2, n + 1)
ev["t"][:n], ev["t"][n] = 1000, 2000  # n events at one time stamp, one at the end
env = EventFlowEnv(ev, sensor_size=(260, 346), window="time", window_size=1000, compute_reward=reward,
                   max_window_events=None)
flow = np.ones((2, 260, 346), np.float32)
before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
env.reset()
env.step(flow)
print((resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before) * 1024 / n)
"""


def bench_window_memory(quick: bool, tiny: bool) -> None:
    """Peak memory per event of one window read, observed (count image) and scored (L_HMC), all
    its events at one time stamp (the documented bound of envs.windows.MAX_WINDOW_EVENTS); each
    in a fresh process, so that the peak is this window's."""
    import subprocess

    for n in (2 * 10**5,) if tiny else (10**6,) if quick else (10**6, 4 * 10**6):
        for reward in (False, True):
            out = subprocess.run([sys.executable, "-c", _WINDOW_MEMORY, str(n), str(int(reward))], cwd=ROOT,
                                 capture_output=True, text=True, check=True)
            what = "read + observation + reward" if reward else "read + observation"
            report("window-memory", f"{what}, {n} events in one window", float(out.stdout.split()[-1]), "B/event")


def bench_tradeoff(quick: bool, tiny: bool, device: str) -> None:
    """AEE and ms per window of the network alone, the network finished by a short solve and the
    model-free solve at two budgets, on the same windows (the full measurement with its picture:
    scripts/tradeoff.py). On devval beside the checkout when it is there, else synthetic-stress."""
    from evflow_cli import tradeoff

    devval = sorted((ROOT.parent / "shared" / "devval").glob("*.h5"))
    data, label = (devval, "devval") if devval and not tiny else ("synthetic-stress", "synthetic-stress")
    modes = ("split", "split+fine:3") if tiny else ("split", "split+fine:3", "net+mid:10", "cmax:20", "cmax:100")
    windows = 2 if tiny else 3 if quick else 8  # the first window of a sequence is warm-up, not timed
    points = tradeoff.measure(data, label, modes, (1,) if tiny else (1, 4), max_windows=windows, device=device,
                              progress=False, echo=lambda line: None, sequences=1 if tiny else None)
    for p in points:
        report("tradeoff", f"{label} dt={p.dt} {p.mode}: AEE", p.mean_aee, "px")
        report("tradeoff", f"{label} dt={p.dt} {p.mode}: time per window", p.ms, "ms")


if __name__ == "__main__":
    sys.exit(main())
