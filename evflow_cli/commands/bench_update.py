"""Benchmark section "update": where one training update of EV-MGRFlowNet spends its time on CPU,
and interleaved A/B of ways to make it cheaper (docs/training.md, "Where a training update's time
goes (CPU)").

The update is ``Learner.update`` at a campaign's settings (default: mgr-strong-teacher, read from
``agents/campaigns/<name>/campaign.json``: EV-MGRFlowNet at CPU width, voxel-grid input, random
96x96 crops of synthetic-train, window sizes 1 2 4, B = 8 envs, L = 4 windows, the teacher loss on
the cached targets), from the campaign's initial weights.

1. Profile: one or more updates under ``torch.profiler``; every operator's own time is put in one
   part: env stepping (reading, cropping, voxelising the next windows), the event batch, the
   logged L_HMC (no grad), the network's forward and backward (convolutions, the recurrent
   layers' compiled kernels, the rest), the teacher loss's forward and backward, the optimizer
   (clip + Adam), and what is left (Python between them). A backward operator belongs to the part
   whose forward operator made its autograd node.
2. A/B: for each variant two learners of the same config (same seed: same initial weights, same
   windows), A and B updating in pairs, alternating which goes first; a row is the median over the
   pairs of the per-pair time ratio A / B (above 1: B is faster) with the quartiles, so load from
   other processes slows both sides of a pair alike. Both learners take the same steps on the same
   data, so each row also gives the largest relative difference of their losses over the steps
   (0: bitwise the same results). Variants:

   - threads: 2 torch threads (A) against 1 (B), switched in the process;
   - intra-op / inter-op, and OpenMP's wait policy (2 threads spinning, the default, against
     ``OMP_WAIT_POLICY=PASSIVE``; and 2 passive threads against 1): settings fixed at a process's
     start, so A and B are two worker processes, driven alternately in pairs the same way;
   - channels-last (the CPU default, with the compiled gate kernels) against NCHW (torch's gate
     expressions);
   - oneDNN's convolutions (the default) against torch's native ones;
   - the teacher's endpoint error as ``Tensor.norm(dim=1)`` (before 2026-12-03) against the square
     root of the summed squares (now; ``norm`` over a 2-channel NCHW dim is ~40x slower);
   - data ahead: a prototype where a worker thread steps the envs to the next window while the
     network runs (with ``compute_reward=False`` the next observation does not depend on the
     action);
   - the logged L_HMC skipped (what logging ``model_hmc`` and ``zero_flow_loss`` costs);
   - flushing denormals to zero;
   - ``torch.compile`` of the network (not with --quick: several minutes to compile): kernels on
     (the compiled kernels' autograd Functions behind ``torch.compiler.disable``, graph breaks
     around them: dynamo cannot trace into numba's dispatcher; the four GRUs' shared helper hits
     dynamo's recompile limit and runs eager) and kernels off (the torch path, NCHW).

``run(report)`` is called by evflow_cli/commands/benchmark.py (``--only update``); standalone:
``python -m evflow_cli.commands.bench_update [--quick] [--tiny] [--pairs N] [--threads N] [--rows KEY ...]``
(``--rows``: the profile and any of the rows, by key: ``ROWS``, ``PROCESS_ROWS``).
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from collections import defaultdict
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from agents.options import command_parser, option, options_from_args, positive_int

SECTION = "update"
ROOT = Path(__file__).resolve().parents[2]
CAMPAIGN = "mgr-strong-teacher"


# -- the update's settings --------------------------------------------------------------------
def campaign_config(name: str = CAMPAIGN):
    """(TrainConfig, initial weights name or None) of campaign ``name``'s recipe, on CPU."""
    from evflow_cli.commands.train import build_parser, config_from_args

    spec = json.loads((ROOT / "agents" / "campaigns" / name / "campaign.json").read_text())
    cfg = config_from_args(build_parser().parse_args([*spec["train"], "--device", "cpu"]))
    if cfg.teacher_cache and not Path(cfg.teacher_cache).is_absolute():  # the recipe's, from the repository root
        cfg = dataclasses.replace(cfg, teacher_cache=str(ROOT / cfg.teacher_cache))
    return cfg, spec.get("init")


def tiny_config(folder: Path):
    """(TrainConfig, None): the campaign's recipe at the smallest sizes: two 48x48 translating-dot
    recordings, 32x32 random crops, B = 2, L = 2, teacher targets solved here with a 2-step solver."""
    from agents.teacher import TeacherSettings, compute_teacher_targets
    from envs.recordings import write_translating_recording

    data = [str(write_translating_recording(folder / f"r{i}.h5", np.random.default_rng(i), sensor_size=(48, 48),
                                            duration_us=300_000, events_per_s=50_000)) for i in range(2)]
    targets = compute_teacher_targets(data, folder / "targets.h5", window_sizes=(1, 2),
                                      settings=TeacherSettings(grids=(2,), steps=2))
    cfg, _ = campaign_config()
    return dataclasses.replace(cfg, data=data, crop=(32, 32), window_size=[1, 2], num_envs=2, unroll=2,
                               teacher_cache=str(targets)), None


def make_learner(cfg, init: str | None):
    from agents.learner import Learner

    learner = Learner(cfg)
    if init:
        from agents.pretrained import load_pretrained

        model, _ = load_pretrained(init)
        learner.policy.model.load_state_dict(model.state_dict())
    return learner


# -- 1. the profile ---------------------------------------------------------------------------
_LABEL = "update-part: "
#: the parts wrapped in a labelled range, (object path in the learner, attribute, part)
_WRAPPED = (("envs", "step", "env stepping (read, crop, voxelise)"), ("policy", "forward", "network"),
            ("objective", None, "teacher loss"), ("optimizer", "step", "optimizer (clip + Adam)"))
_KERNELS = ("_GRUUpdates", "_OutputGate", "_PackRefinerInput", "_RefinerUpdate")
_CONV = ("aten::mkldnn_convolution", "aten::_slow_conv2d_forward", "aten::convolution_backward",
         "aten::_slow_conv2d_backward", "aten::thnn_conv2d")


@contextlib.contextmanager
def _patched(obj, name: str, value):
    """``obj.name = value`` inside the block; afterwards the attribute as it was stored (a class's
    own descriptor, e.g. a classmethod, or no instance attribute at all)."""
    own = name in vars(obj)
    old = vars(obj)[name] if own else None
    setattr(obj, name, value)
    try:
        yield
    finally:
        if own:
            setattr(obj, name, old)
        else:
            delattr(obj, name)


def _labelled(fn, part: str):
    def run(*args, **kwargs):
        with torch.profiler.record_function(_LABEL + part):
            return fn(*args, **kwargs)
    return run


def profile_update(learner, updates: int = 1) -> tuple[dict[str, float], float]:
    """({part: seconds per update}, wall seconds per update) of ``updates`` profiled updates."""
    import agents.learner as learner_module
    from losses import EventBatch

    with contextlib.ExitStack() as stack:
        for path, attribute, part in _WRAPPED:
            obj = getattr(learner, path)
            if attribute is None:
                stack.enter_context(_patched(learner, path, _labelled(obj, part)))
            else:
                stack.enter_context(_patched(obj, attribute, _labelled(getattr(obj, attribute), part)))
        clip = torch.nn.utils.clip_grad_norm_
        stack.enter_context(_patched(torch.nn.utils, "clip_grad_norm_", _labelled(clip, "optimizer (clip + Adam)")))
        stack.enter_context(_patched(torch.autograd, "backward", _labelled(torch.autograd.backward, "backward")))
        for name in ("window_loss", "zero_flow_loss"):
            fn = getattr(learner_module, name)
            stack.enter_context(_patched(learner_module, name, _labelled(fn, "logged L_HMC (no grad)")))
        stack.enter_context(_patched(EventBatch, "from_windows",
                                     _labelled(EventBatch.from_windows, "event batch (padded windows)")))
        with torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CPU]) as prof:
            start = time.perf_counter()
            for _ in range(updates):
                learner.update()
            wall = (time.perf_counter() - start) / updates
    return {part: seconds / updates for part, seconds in _attribute(prof.events()).items()}, wall


def _attribute(events) -> dict[str, float]:
    """Seconds of operator self time per part (module docstring, 1.)."""

    def ancestors(event):
        while event is not None:
            yield event
            event = event.cpu_parent

    forward_part = {}  # sequence number of an autograd node -> the part that made it
    for event in events:
        if event.sequence_nr >= 0 and not event.name.startswith("autograd::"):
            label = next((e.name for e in ancestors(event) if e.name.startswith(_LABEL)), None)
            if label is not None:
                forward_part.setdefault(event.sequence_nr, label[len(_LABEL):])
    parts = defaultdict(float)
    for event in events:
        seconds = event.self_cpu_time_total / 1e6
        chain = list(ancestors(event))
        label = next((e.name[len(_LABEL):] for e in chain if e.name.startswith(_LABEL)), "rest (Python between parts)")
        kernel = any(e.name.replace("Backward", "") in _KERNELS or
                     e.name.endswith(tuple(k + "Backward" for k in _KERNELS)) for e in chain)
        conv = event.name in _CONV
        if label == "backward":
            node = next((e for e in chain if e.name.startswith("autograd::engine::evaluate_function")), None)
            made_by = forward_part.get(node.sequence_nr, "network") if node is not None else "network"
            label = "teacher loss, backward" if made_by == "teacher loss" else "network backward"
        elif label == "network":
            label = "network forward"
        elif label == "teacher loss":
            label = "teacher loss, forward (target lookup, upsampling, endpoint error)"
        if label in ("network forward", "network backward"):
            label += ": convolutions" if conv else ": recurrent kernels (numba)" if kernel else ": other ops"
        parts[label] += seconds
    return dict(parts)


def report_profile(report, parts: dict[str, float], wall: float, label: str) -> None:
    report(SECTION, f"profile {label}: one update, wall (under the profiler)", wall, "s")
    counted = sum(parts.values())
    parts = {**parts, "rest (Python between parts)": parts.get("rest (Python between parts)", 0.0) + wall - counted}
    for part, seconds in sorted(parts.items(), key=lambda kv: -kv[1]):
        report(SECTION, f"profile: {part} ({1e3 * seconds:.0f} ms)", 100 * seconds / wall, "%")


# -- 2. interleaved A/B -----------------------------------------------------------------------
def _timed(fn):
    start = time.perf_counter()
    out = fn()
    return time.perf_counter() - start, out


def interleaved(a, b, pairs: int, seconds=None) -> tuple[list[float], float]:
    """(per-pair time ratios A / B, largest relative loss difference) of callables returning an
    update's logged dict, after one warm-up call each; the order alternates pair by pair.
    ``seconds(out)``: the time a call reports itself (default: the call's wall time here)."""
    losses = {"a": [a()["loss"]], "b": [b()["loss"]]}
    ratios = []
    for k in range(pairs):
        order = (("a", a), ("b", b)) if k % 2 == 0 else (("b", b), ("a", a))
        times = {}
        for name, fn in order:
            times[name], out = _timed(fn)
            if seconds is not None:
                times[name] = seconds(out)
            losses[name].append(out["loss"])
        ratios.append(times["a"] / times["b"])
    diff = max(abs(x - y) / max(abs(x), 1e-12) for x, y in zip(losses["a"], losses["b"]))
    return ratios, diff


def report_ab(report, row: str, ratios: list[float], diff: float | None) -> None:
    q1, median, q3 = statistics.quantiles(ratios, n=4) if len(ratios) > 1 else (ratios[0],) * 3
    same = "" if diff is None else "bitwise same losses" if diff == 0 else f"losses within {diff:.1e} rel."
    report(SECTION, f"A/B {row}: A/B time, median of {len(ratios)} pairs [{q1:.2f}, {q3:.2f}]; {same}", median, "x")


def _threads(n: int, learner):
    def run():
        previous = torch.get_num_threads()
        torch.set_num_threads(n)
        try:
            return learner.update()
        finally:
            torch.set_num_threads(previous)
    return run


def _old_endpoint_error(flow, target, weight):
    """The teacher's endpoint error before 2026-12-03 (torch's vector norm over the channel dim)."""
    return ((flow - target).norm(dim=1, keepdim=True) * weight).sum() / weight.sum().clamp_min(1)


def _with(learner, *patches):
    """learner.update with (object, attribute, value) patches in place during the call."""
    def run():
        with contextlib.ExitStack() as stack:
            for obj, name, value in patches:
                stack.enter_context(_patched(obj, name, value))
            return learner.update()
    return run


def _flush_denormal(learner):
    def run():
        torch.set_flush_denormal(True)
        try:
            return learner.update()
        finally:
            torch.set_flush_denormal(False)
    return run


class StepAhead:
    """Prototype: a vector env stepped one window ahead in a worker thread. ``step`` returns the
    step prepared while the network ran and starts the next one; valid while the env computes no
    reward (the learner's envs), whose next observation does not depend on the action. Not a
    checkpoint-safe env (the envs are a window ahead of what the learner has seen)."""

    def __init__(self, envs) -> None:
        self.envs, self.pool, self.pending = envs, ThreadPoolExecutor(1), None
        self.zero = np.zeros((envs.num_envs, *envs.single_action_space.shape), np.float32)

    def step(self, action):
        out = self.pending.result() if self.pending is not None else self.envs.step(action)
        self.pending = self.pool.submit(self.envs.step, self.zero)
        return out

    def close(self) -> None:
        if self.pending is not None:
            self.pending.result()
        self.pool.shutdown()
        self.envs.close()


def _skip_logged_hmc():
    """Patches of agents.learner that skip the logged L_HMC (zero flow and the finest flow's)."""
    import agents.learner as learner_module
    from losses import LossOutput

    def zero(like, window, *args, **kwargs):
        per_sample = torch.zeros(like.shape[0])
        return LossOutput(per_sample.mean(), per_sample, {})

    def logged(flow, window, *args, **kwargs):
        return zero(flow, window)

    return (learner_module, "zero_flow_loss", zero), (learner_module, "window_loss", logged)


def _compiled(learner, kernels: bool):
    """Learner.update with the network under torch.compile (kernels on: their autograd Functions
    behind torch.compiler.disable; off: the torch path, NCHW, during the forward)."""
    from agents import layers
    from losses import warp
    from losses.kernel_switch import cpu_kernels

    if kernels:
        for cls in (*(getattr(layers, name) for name in _KERNELS), warp._ForwardWarpCompiled):
            if not getattr(cls.apply, "_torchdynamo_disable", False):
                cls.apply = torch.compiler.disable(cls.apply)
    model = learner.policy.model
    compiled = torch.compile(model)

    def forward(x, state):
        with contextlib.nullcontext() if kernels else cpu_kernels(False):
            return compiled(x, state)

    learner.policy.model = _Forward(model, forward)
    return learner.update


class _Forward(torch.nn.Module):
    """``model`` (its parameters, its state dict) whose forward is ``forward``."""

    def __init__(self, model, forward) -> None:
        super().__init__()
        self.inner, self._forward = model, forward

    def forward(self, x, state):
        return self._forward(x, state)


def _native_convolutions(learner):
    def run():
        with torch.backends.mkldnn.flags(enabled=False):
            return learner.update()
    return run


def _row_table(results_pairs: int):
    """{key: (row, make A from a learner, make B from a learner, pairs or None)} of the in-process rows."""
    from agents import objectives

    return {
        "threads": ("threads: 2 (A) vs 1 (B) torch threads", lambda le: _threads(2, le), lambda le: _threads(1, le),
                    None),
        "layout": ("layout: NCHW, torch gates (A) vs channels-last + kernels (B, default)",
                   lambda le: (setattr(le.policy.model, "channels_last", False), le.update)[1],
                   lambda le: le.update, None),
        "convolutions": ("convolutions: torch's native, oneDNN off (A) vs oneDNN (B, default)", _native_convolutions,
                         lambda le: le.update, None),
        "endpoint": ("teacher endpoint error: Tensor.norm (A, before) vs sqrt of summed squares (B, now)",
                     lambda le: _with(le, (objectives, "_endpoint_error", _old_endpoint_error)),
                     lambda le: le.update, results_pairs),
        "ahead": ("data ahead: envs stepped in the update (A) vs one window ahead in a worker thread (B)",
                  lambda le: le.update, lambda le: (setattr(le, "envs", StepAhead(le.envs)), le.update)[1], None),
        "logged": ("logged L_HMC: computed (A) vs skipped (B)", lambda le: le.update,
                   lambda le: _with(le, *_skip_logged_hmc()), None),
        "denormals": ("denormals: kept (A) vs flushed to zero (B)", lambda le: le.update, _flush_denormal, None),
        "compile-kernels": ("torch.compile: eager (A) vs compiled network, kernels on (B)", lambda le: le.update,
                            lambda le: _compiled(le, True), None),
        "compile-torch": ("torch.compile: eager (A) vs compiled network, kernels off (B)", lambda le: le.update,
                          lambda le: _compiled(le, False), None),
    }


#: the in-process rows' keys (``--rows``); the torch.compile ones take minutes to compile
ROWS = tuple(_row_table(0))
PROCESS_ROWS = ("intra-inter", "omp-wait", "passive-one")


def in_process_rows(report, cfg, init, *, pairs: int, rows=ROWS, results_pairs: int = 0) -> None:
    """The in-process rows named in ``rows``; ``results_pairs``: at least this many pairs in the
    endpoint-error row (the change kept, so its loss comparison runs longer)."""
    for key in rows:
        row, make_a, make_b, row_pairs = _row_table(results_pairs)[key]
        learners = [make_learner(cfg, init), make_learner(cfg, init)]
        start = time.perf_counter()
        try:
            ratios, diff = interleaved(make_a(learners[0]), make_b(learners[1]), max(pairs, row_pairs or 0))
        finally:
            for learner in learners:
                learner.close()
        report_ab(report, row, ratios, diff)
        if key.startswith("compile"):
            report(SECTION, f"{row}: the row's wall time, compiling included", time.perf_counter() - start, "s")


# -- settings fixed at a process's start: two worker processes, driven in pairs ----------------
def _worker(config: str) -> int:
    """Worker loop: one update per line read from stdin, its seconds and loss written back."""
    from agents.train_config import TrainConfig

    spec = json.loads(config)
    torch.set_num_threads(spec["intra"])
    torch.set_num_interop_threads(spec["inter"])
    learner = make_learner(TrainConfig(**spec["config"]), spec["init"])
    print(_REPLY, "ready", flush=True)
    for line in sys.stdin:
        if line.strip() != "update":
            break
        seconds, out = _timed(learner.update)
        print(_REPLY, json.dumps({"seconds": seconds, "loss": out["loss"]}), flush=True)
    learner.close()
    return 0


_REPLY = "bench-update-worker:"  # marks the worker's replies among anything else it prints


class _Process:
    def __init__(self, cfg, init, intra: int, inter: int, environ: dict[str, str]) -> None:
        spec = json.dumps({"config": cfg.to_dict(), "init": init, "intra": intra, "inter": inter})
        env = {**os.environ, **environ, "PYTHONPATH": str(ROOT)}
        self.proc = subprocess.Popen([sys.executable, "-m", "evflow_cli.commands.bench_update", "--worker", spec],
                                     stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, env=env, cwd=ROOT)
        if self._reply() != "ready":
            raise RuntimeError(f"bench_update worker failed to start (exit {self.proc.wait()})")

    def _reply(self) -> str:
        for line in self.proc.stdout:
            if line.startswith(_REPLY):
                return line[len(_REPLY):].strip()
        return ""

    def update(self) -> dict:
        self.proc.stdin.write("update\n")
        self.proc.stdin.flush()
        return json.loads(self._reply())

    def close(self) -> None:
        self.proc.stdin.close()
        self.proc.wait()


def process_rows(report, cfg, init, *, pairs: int, rows=PROCESS_ROWS) -> None:
    """The rows of settings fixed at a process's start (``PROCESS_ROWS``) named in ``rows``."""
    settings = {
        "intra-inter": ("intra-op vs inter-op: 2 intra, 1 inter (A) vs 1 intra, 2 inter (B)", (2, 1, {}), (1, 2, {})),
        "omp-wait": ("OpenMP wait, 2 threads: active spin, the default (A) vs OMP_WAIT_POLICY=PASSIVE (B)",
                     (2, 1, {}), (2, 1, {"OMP_WAIT_POLICY": "PASSIVE"})),
        "passive-one": ("1 thread (A) vs 2 threads with OMP_WAIT_POLICY=PASSIVE (B)",
                        (1, 1, {}), (2, 1, {"OMP_WAIT_POLICY": "PASSIVE"})),
    }
    for row, a, b in (settings[key] for key in rows):
        workers = [_Process(cfg, init, *a), _Process(cfg, init, *b)]
        try:  # the ratio of the workers' own update times (not the pipe's round trips)
            ratios, diff = interleaved(workers[0].update, workers[1].update, pairs, seconds=lambda out: out["seconds"])
        finally:
            for worker in workers:
                worker.close()
        report_ab(report, f"{row} [processes]", ratios, diff)


def run(report, *, quick: bool = False, tiny: bool = False, pairs: int | None = None, campaign: str = CAMPAIGN,
        rows: tuple[str, ...] | None = None) -> None:
    """The profile and the A/B rows (module docstring). rows: keys of ``ROWS`` and
    ``PROCESS_ROWS``, and "profile" (default: all but the torch.compile rows with ``quick`` or
    ``tiny``). quick: 3 pairs a row; tiny: the smallest sizes, one pair, one process row (checks
    the section runs)."""
    pairs = pairs or (1 if tiny else 3 if quick else 10)
    if rows is None:
        rows = ("profile", *ROWS, *PROCESS_ROWS)
        if quick or tiny:
            rows = tuple(key for key in rows if not key.startswith("compile") and not (tiny and key in PROCESS_ROWS[1:]))
    print(f"# {SECTION}: {torch.get_num_threads()} torch threads; campaign {campaign if not tiny else '(tiny sizes)'}",
          flush=True)
    with tempfile.TemporaryDirectory() as tmp:
        cfg, init = tiny_config(Path(tmp)) if tiny else campaign_config(campaign)
        if "profile" in rows:
            learner = make_learner(cfg, init)
            try:
                learner.update()  # warm-up
                parts, wall = profile_update(learner, 1 if tiny or quick else 2)
            finally:
                learner.close()
            report_profile(report, parts, wall, f"{torch.get_num_threads()} thread(s)")
        in_process_rows(report, cfg, init, pairs=pairs, rows=[key for key in ROWS if key in rows],
                        results_pairs=0 if quick or tiny else 24)
        process_rows(report, cfg, init, pairs=pairs, rows=[key for key in PROCESS_ROWS if key in rows])


def _print_row(section: str, row: str, value: float, unit: str) -> None:
    print(f"{section:<7} | {row:<110} | {value:9.3f} {unit}", flush=True)


@dataclass
class BenchUpdateOptions:
    """What python -m evflow_cli.commands.bench_update profiles and compares."""

    quick: bool = False
    """3 pairs a row, no torch.compile rows"""
    tiny: bool = False
    """the smallest sizes, one pair a row (a check, not a measurement)"""
    pairs: int | None = option(None, type=positive_int)
    """A/B pairs a row (default 10; --quick 3)"""
    campaign: str = CAMPAIGN
    """the campaign (agents/campaigns/NAME) whose recipe is the update"""
    rows: list[str] | None = option(None, choices=["profile", *ROWS, *PROCESS_ROWS])
    """the profile and the rows to run (default: all; with --quick or --tiny no torch.compile rows)"""
    threads: int | None = option(None, type=positive_int)
    """torch CPU threads of the profile and the rows (default: torch's choice; 1 on a busy machine)"""
    worker: str | None = None
    """internal: run as one side of a process row (a JSON spec; the section starts these itself)"""


def build_parser() -> argparse.ArgumentParser:
    return command_parser(BenchUpdateOptions, __doc__)


def main(argv=None) -> int:
    args = options_from_args(BenchUpdateOptions, build_parser().parse_args(argv))
    if args.worker:
        return _worker(args.worker)
    if args.threads:
        torch.set_num_threads(args.threads)
    run(_print_row, quick=args.quick, tiny=args.tiny, pairs=args.pairs, campaign=args.campaign,
        rows=None if args.rows is None else tuple(args.rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
