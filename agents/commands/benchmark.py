"""Speed benchmarks, one section per part of the project. Prints `section | row | value unit`.

  python scripts/benchmark.py                      # every section
  python scripts/benchmark.py --only foundation env
  python scripts/benchmark.py --quick              # fewer repetitions

Sections: foundation (project h5 windows + count images), simulator (with synthetic-dr-train
generation per sensor size), losses, agents, env,
training, readers, prophesee (RAW reading at 1280x720), predict (agents/predict.py end to end).
Timings are wall-clock on whatever machine runs them; compare rows of one run.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import numpy as np
import torch

SECTIONS = ("foundation", "simulator", "losses", "agents", "env", "training", "readers", "prophesee", "predict")


def report(section: str, row: str, value: float, unit: str) -> None:
    print(f"{section:<11} | {row:<60} | {value:12.3f} {unit}", flush=True)


def _recording(path: Path, seconds: float = 4.0, rate: float = 2e6, size=(260, 346)):
    """A 346x260 recording at `rate` events/s (uniform random events)."""
    from envs.events import Events
    from envs.h5format import H5Writer

    rng = np.random.default_rng(0)
    h, w = size
    with H5Writer(path, size, name="bench") as writer:
        chunk_s = 0.5
        for k in range(int(seconds / chunk_s)):
            n = int(rate * chunk_s)
            t = np.sort(rng.integers(int(k * chunk_s * 1e6), int((k + 1) * chunk_s * 1e6), n))
            writer.append_events(Events.create(rng.integers(0, w, n), rng.integers(0, h, n), t, rng.integers(0, 2, n), size))
    return path


def bench_foundation(quick: bool) -> None:
    from envs.h5format import H5Reader
    from envs.representations import count_image
    from envs.windows import iter_windows

    with tempfile.TemporaryDirectory() as tmp:
        path = _recording(Path(tmp) / "rec.h5", seconds=2.0 if quick else 4.0)
        with H5Reader(path) as reader:
            for mode, size, label in (("time", 10_000, "10 ms"), ("count", 30_000, "30k-event")):
                start = time.perf_counter()
                n = 0
                for window in iter_windows(reader, mode, size):
                    count_image(window.events)
                    n += 1
                elapsed = time.perf_counter() - start
                report("foundation", f"project h5 346x260 @2 Mev/s: {label} windows + count image", n / elapsed, "windows/s")


def bench_env(quick: bool) -> None:
    import gymnasium

    import envs  # noqa: F401  (registers the ids)
    from envs.env import EventFlowEnv

    steps = 20 if quick else 60
    with tempfile.TemporaryDirectory() as tmp:
        path = str(_recording(Path(tmp) / "rec.h5", seconds=2.0, rate=1e6))
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


def bench_training(quick: bool) -> None:
    """Training windows/s (rollout + loss + backward + step) at 128x128, batch 8, CPU width,
    per model; and a 2-process DDP run beside the single process."""
    import json
    import os
    import subprocess

    from agents.learner import Learner, TrainConfig
    from tests.recordings import write_translating_recording

    steps = 2 if quick else 4
    with tempfile.TemporaryDirectory() as tmp:
        data = [str(write_translating_recording(Path(tmp) / f"r{i}.h5", np.random.default_rng(i), sensor_size=(128, 128),
                                                 duration_us=2_000_000, events_per_s=400_000)) for i in range(2)]
        for model in ("ev-mgrflownet", "convgru-ev-flownet", "ev-flownet", "xlif-ev-flownet"):
            learner = Learner(TrainConfig(model=model, data=data, num_envs=8, unroll=10, width="cpu", flips=False))
            learner.update()  # warm-up
            start = time.perf_counter()
            for _ in range(steps):
                learner.update()
            report("training", f"{model} cpu width 128x128 B=8 L=10", 80 * steps / (time.perf_counter() - start), "windows/s")
            learner.close()
        root = Path(__file__).resolve().parents[1]
        for nproc in (1, 2):
            out = Path(tmp) / f"ddp{nproc}"
            cmd = [sys.executable, "-m", "torch.distributed.run", f"--nproc_per_node={nproc}", "--master_port=29555",
                   str(root / "scripts" / "train.py"), "--data", *data, "--num-envs", str(8 // nproc), "--steps", str(steps + 1),
                   "--out", str(out), "--val-data", "", "--no-progress", "--no-flips", "--device", "cpu"]
            env = {**os.environ, "OMP_NUM_THREADS": str(max(1, 2 // nproc)), "PYTHONPATH": str(root)}
            subprocess.run(cmd, check=True, capture_output=True, env=env)
            rows = [json.loads(line) for line in (out / "metrics.jsonl").read_text().splitlines()]
            rate = rows[-1]["windows_per_s"] * nproc  # rank 0 logs its own windows; ranks roll equal shares
            report("training", f"ev-mgrflownet 128x128, 8 envs in all, torchrun {nproc} process(es)", rate, "windows/s")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--only", nargs="+", choices=SECTIONS, default=list(SECTIONS))
    parser.add_argument("--quick", action="store_true", help="fewer repetitions and smaller inputs")
    parser.add_argument("--threads", type=int, default=None, help="torch threads (default: torch's choice)")
    args = parser.parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    print(f"# torch {torch.__version__}, {torch.get_num_threads()} threads", flush=True)
    for section in args.only:
        if section == "foundation":
            bench_foundation(args.quick)
        elif section == "env":
            bench_env(args.quick)
        elif section == "training":
            bench_training(args.quick)
        elif section == "simulator":
            from agents.commands import bench_simulator

            bench_simulator.run(report, quick=args.quick)
        elif section == "losses":
            from agents.commands import bench_losses

            bench_losses.run(report, quick=args.quick)
        elif section == "agents":
            from agents.commands import bench_agents

            bench_agents.run(report, reps=1 if args.quick else 2)
        elif section == "readers":
            from agents.commands import bench_readers

            bench_readers.run(report)
        elif section in ("prophesee", "predict"):
            from agents.commands import bench_prophesee

            bench_prophesee.run(report, num_events=4_000_000 if args.quick else bench_prophesee.DEFAULT_EVENTS,
                                sections=(section,))
    return 0


if __name__ == "__main__":
    sys.exit(main())
