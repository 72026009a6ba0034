"""Accuracy against time per window: the network alone, the network finished by K steps of a
solve on the window's own events, and the model-free solve at full and reduced iterations, on
the same windows in one run (``scripts/tradeoff.py``; a small version is the benchmark's
``tradeoff`` section).

Modes (one point each; ``K`` and ``N`` are solver steps):

- ``default``: the shipped default in its mode (``agents/weights/default.json``: the network's
  proposal and the finish chosen by window length, docs/finish.md).
- ``zero``: zero flow (its AEE is the scale: a mode above it invents motion).
- ``net``: the network, one pass per window.
- ``split``: the network stepped once per ground-truth interval (``--split dt``, the default's mode
  before 2026-12-05).
- ``coarseF``: the network on the window's events binned F x F pixels to one, its flow upsampled
  (agents/wrappers/coarse.py); ``coarseF:S``: stepped through S equal sub-windows, their flows
  composed; ``coarse3:2+cmax:K/E`` finishes that proposal.
- ``split+fine:K`` / ``split+cmax:K``: ``split`` finished by K steps of the refinement solver
  'fine' (one 16-cell level on sensor pixels) or 'cmax' (the coarse-to-fine solve started from
  the network's flow; agents/wrappers/refine.py). ``net+...`` starts from one pass instead.
  ``mid:K``: the solve's two finer levels only; ``gd:K``: the K unrolled gradient steps training
  takes with ``--finish-steps K`` (losses/finish.py), here without a graph. ``/E`` after K: the solve sees an even subsample
  of at most E of the window's events (cheaper steps); ``xS`` then: the solve's step size times S.
  A suffix ``@P`` holds the solve to the
  proposal with prior weight P (``split+cmax:20/8000@1``).
- a suffix ``+still`` on any network mode (``split+fine:3+still``): zero flow wherever the mode's
  flow does not lower the window's loss below zero flow's (agents/wrappers/still.py).
- ``net+block:K`` (any proposal before ``+``): the proposal finished by K iterations of the
  learned update block of ``--block`` (agents/update_block.py, scripts/train_block.py);
  ``default+block:K``: the default's proposals (by window length) finished by it instead of the
  default's solves; ``default+block:K+solve``: K iterations of the block, then the default's solve.
- ``cmax:N``: per-window contrast maximisation from zero flow with N steps shared 40/30/30 over
  its three levels (``cmax:100`` is the ``--cmax`` row, agents/cmax.py).

Sequences are interleaved: every mode runs on a sequence before the next sequence starts, so a
slow spell of the machine touches every mode alike. ``ms`` is the mean time a mode takes to give
a window's flow (the first window of each sequence left out: warm-up), the network's proposal
included in a finished mode's time.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from agents.cmax import CMaxSettings, ContrastMaximisationPolicy
from agents.evaluation import evaluate
from agents.policy import RecurrentPolicy
from agents.wrappers.coarse import CoarsePolicy
from agents.wrappers.refine import BLOCK, GRADIENT, Finish, FinishedPolicy, RefinedPolicy
from agents.wrappers.still import StillGuard
from agents.wrappers.subwindows import SubWindowPolicy
from envs.atomic import temporary_path
from envs.dataset import resolve_data

__all__ = ["DEFAULT_MODES", "Point", "build_mode", "load_points", "measure", "table", "plot"]

DEFAULT_MODES = ("zero", "net", "split", "split+fine:3", "split+fine:10", "split+fine:30", "split+cmax:3",
                 "split+cmax:10", "split+cmax:30", "cmax:10", "cmax:30", "cmax:100")


def cmax_settings(steps: int) -> CMaxSettings:
    """The ``--cmax`` solve with ``steps`` in all, shared 40/30/30 over its levels (each >= 1)."""
    first, second = max(1, round(0.4 * steps)), max(1, round(0.3 * steps))
    return CMaxSettings(steps=(first, second, max(1, steps - first - second)))


def build_mode(mode: str, model: str | None, dt: int, device: str = "cpu", block=None):
    """The policy of ``mode`` (module docstring) for windows of ``dt`` ground-truth intervals;
    None for zero flow. ``block``: the learned update block of the ``+block:K`` modes. ValueError
    naming the mode when it is not one of the forms above."""
    kind, _, rest = mode.partition(":")
    if mode == "zero":
        return None
    if "+block:" in mode and block is None:
        raise ValueError(f"mode {mode!r}: a learned finish needs the block (--block FILE of scripts/train_block.py)")
    if mode.startswith("default+block:"):  # the default's proposals, finished by the block (then its solve)
        from agents.pretrained import default_finish

        steps, plus, then = mode[len("default+block:"):].partition("+")
        if not steps.isdigit() or (plus and then != "solve"):
            raise ValueError(f"mode {mode!r}: default+block:K[+solve] takes a number of iterations")
        shipped = [Finish.from_dict(f) if not isinstance(f, Finish) else f for f in default_finish()]
        finishes = [dataclasses.replace(f, block_steps=int(steps)) if plus else
                    dataclasses.replace(f, solver=BLOCK, steps=int(steps)) for f in shipped]
        return FinishedPolicy(_network(model, device), finishes, block=block)
    if mode == "default":  # the shipped default's mode (agents/weights/default.json: split and finish)
        from agents.pretrained import default_finish, default_split

        policy = _network(model, device)
        if default_split() == "dt":
            policy = SubWindowPolicy(policy, splits=dt)
        return FinishedPolicy(policy, default_finish()) if default_finish() else policy
    if mode.endswith("+still"):
        inner = build_mode(mode[: -len("+still")], model, dt, device)
        if inner is None or isinstance(inner, ContrastMaximisationPolicy):
            raise ValueError(f"mode {mode!r}: +still guards a network mode (net..., split...)")
        return StillGuard(inner)
    if kind == "cmax":
        if not rest.isdigit() or int(rest) < 1:
            raise ValueError(f"mode {mode!r}: cmax takes a number of steps, e.g. cmax:30")
        return ContrastMaximisationPolicy(cmax_settings(int(rest)), device=device)
    start, plus, finish = mode.partition("+")
    factor, _, splits = (start[len("coarse"):] if start.startswith("coarse") else "").partition(":")
    splits = splits or "1"
    if start not in ("net", "split") and not (factor.isdigit() and 1 <= int(factor) <= 16 and splits.isdigit()
                                              and int(splits) >= 1):
        raise ValueError(f"unknown mode {mode!r}; forms: zero, net, split, coarseF[:S], net+fine:K, split+cmax:K[@P], "
                         "coarse3:2+cmax:K, cmax:N")
    policy = _network(model, device)
    if start == "split":
        policy = SubWindowPolicy(policy, splits=dt)
    elif factor:
        policy = CoarsePolicy(policy, int(factor), int(splits))
    if not plus:
        return policy
    solver, _, steps = finish.partition(":")
    steps, _, prior = steps.partition("@")
    steps, _, scale = steps.partition("x")
    steps, _, events = steps.partition("/")
    try:
        lr_scale = float(scale) if scale else 1.0
    except ValueError:
        lr_scale = -1.0
    if solver == GRADIENT and steps.isdigit() and (events.isdigit() or not events) and lr_scale > 0 and not prior:
        return FinishedPolicy(policy, [Finish(GRADIENT, int(steps), int(events) if events else None, None, lr_scale)])
    if solver == BLOCK and steps.isdigit() and (events.isdigit() or not events) and not scale and not prior:
        return FinishedPolicy(policy, [Finish(BLOCK, int(steps), int(events) if events else None)], block=block)
    if (solver not in RefinedPolicy.SOLVERS or not steps.isdigit() or not (events.isdigit() or not events)
            or not lr_scale > 0):
        raise ValueError(f"mode {mode!r}: the finish is fine:K, mid:K or cmax:K (K steps), optionally /E (events "
                         "the solve sees), xS (step size times S) and @P (prior weight)")
    return RefinedPolicy(policy, steps=int(steps), solver=solver, prior_weight=float(prior or 0.0),
                         max_events=int(events) if events else None, lr_scale=lr_scale)


def _network(model: str | None, device: str):
    """The network of ``model``: a shipped name (None: the default) or a checkpoint file written by
    training (a registered model only: agents.checkpoint)."""
    if model is not None and os.path.isfile(model):
        from agents.checkpoint import load_model

        net, payload = load_model(model, map_location=device)
        cfg = payload.get("config") or {}
        return RecurrentPolicy(net, device=device, input_key=cfg.get("input", "count_image"),
                               voxel_bins=cfg.get("voxel_bins", 5))
    return RecurrentPolicy.from_pretrained(model, device=device)


@dataclass
class Point:
    """One mode on one data set at one dt: means over windows, pooled over sequences."""

    data: str
    dt: int
    mode: str
    aee: list = field(default_factory=list)  # per sequence
    hmc: list = field(default_factory=list)
    hmc_zero: list = field(default_factory=list)
    ms_sum: float = 0.0
    ms_count: int = 0
    windows: int = 0

    @property
    def ms(self) -> float:
        return self.ms_sum / self.ms_count if self.ms_count else float("nan")

    @property
    def mean_aee(self) -> float:
        values = [v for v in self.aee if math.isfinite(v)]
        return float(np.mean(values)) if values else float("nan")

    def as_dict(self) -> dict:
        return {"data": self.data, "dt": self.dt, "mode": self.mode, "aee": self.mean_aee, "ms": self.ms,
                "aee_per_sequence": self.aee, "hmc_per_sequence": self.hmc, "hmc_zero_per_sequence": self.hmc_zero,
                "windows": self.windows}


def measure(data: str, label: str, modes, dts, *, model: str | None = None, max_windows: int | None = None,
            device: str = "cpu", progress: bool = True, echo=print, sequences: int | None = None,
            block=None) -> list[Point]:
    """Every mode at every dt on every sequence of ``data`` (interleaved by sequence; the first
    ``sequences`` only, when given)."""
    total = len(resolve_data(data))
    points = {(dt, mode): Point(label, dt, mode) for dt in dts for mode in modes}
    for dt in dts:  # warm-up, not counted: kernels compiled and caches filled for every mode alike
        for mode in modes:
            evaluate(build_mode(mode, model, dt, device, block), data, window="frames", window_size=dt, max_windows=2,
                     progress=False, shard=(0, total))
    for index in range(total if sequences is None else min(sequences, total)):
        for dt in dts:
            for mode in modes:
                policy = build_mode(mode, model, dt, device, block)
                [row] = evaluate(policy, data, window="frames", window_size=dt, max_windows=max_windows,
                                 progress=progress, shard=(index, total))
                point = points[(dt, mode)]
                point.aee.append(row.mean("aee"))
                point.hmc.append(row.mean("hmc"))
                point.hmc_zero.append(row.mean("hmc_zero"))
                point.ms_sum += row.sums.get("ms", 0.0)
                point.ms_count += row.counts.get("ms", 0)
                point.windows += row.windows
            echo(f"[tradeoff] {label} {index + 1}/{total} {row.name} dt={dt}: "
                 + ", ".join(f"{m} {points[(dt, m)].aee[-1]:.3f}" for m in modes))
    return list(points.values())


def table(points: list[Point], reference: str = "cmax:100") -> str:
    """Markdown: per data set and dt, each mode's AEE, its ratio to ``reference``'s, the
    sequences where it is below zero flow's AEE, and ms per window with the ratio of times."""
    lines = []
    for data, dt in dict.fromkeys((p.data, p.dt) for p in points):
        rows = [p for p in points if (p.data, p.dt) == (data, dt)]
        ref = next((p for p in rows if p.mode == reference), None)
        zero = next((p for p in rows if p.mode == "zero"), None)
        n = len(rows[0].aee)
        lines += [f"\n{data}, dt = {dt} ({n} sequences, {rows[0].windows} windows)\n",
                  f"| mode | AEE | / {reference} | below zero flow | ms / window | time / {reference} |",
                  "|---|---:|---:|---:|---:|---:|"]
        for p in rows:
            ratio = p.mean_aee / ref.mean_aee if ref else float("nan")
            below = (sum(a < z for a, z in zip(p.aee, zero.aee)) if zero and p is not zero else None)
            time_ratio = p.ms / ref.ms if ref and ref.ms else float("nan")
            lines.append(f"| {p.mode} | {p.mean_aee:.3f} | {ratio:.2f}x | {'-' if below is None else f'{below}/{n}'} "
                         f"| {p.ms:.0f} | {time_ratio:.2f} |")
    return "\n".join(lines).lstrip("\n")


FAMILIES = ("network alone", "+ fine", "+ mid", "+ cmax", "cmax alone", "the default's mode", "other")


def family(mode: str) -> str | None:
    """The line of the plot a mode belongs to (None: zero flow, drawn as a level)."""
    if mode == "zero":
        return None
    if mode == "default":
        return "the default's mode"
    if mode.startswith("cmax:"):
        return "cmax alone"
    if mode in ("net", "split") or (mode.startswith("coarse") and "+" not in mode):
        return "network alone"
    if "+still" not in mode:
        for solver in ("fine", "mid", "cmax"):
            if f"+{solver}:" in mode:
                return f"+ {solver}"
    return "other"


def plot(points: list[Point], path: Path, reference: str = "cmax:100") -> Path | None:
    """AEE against ms per window (log), one panel per data set and dt; None without matplotlib."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
        import matplotlib.ticker
    except ImportError:
        return None
    panels = list(dict.fromkeys((p.data, p.dt) for p in points))
    fig, axes = plt.subplots(1, len(panels), figsize=(4.8 * len(panels), 4.0), squeeze=False)
    for ax, (data, dt) in zip(axes[0], panels):
        rows = [p for p in points if (p.data, p.dt) == (data, dt) and math.isfinite(p.mean_aee)]
        for name, marker in zip(FAMILIES, "osvD^*x"):
            members = sorted((p for p in rows if family(p.mode) == name), key=lambda p: p.ms)
            if not members:
                continue
            ax.plot([p.ms for p in members], [p.mean_aee for p in members], marker + ("-" if name != "other" else ""),
                    label=name, ms=9 if marker == "*" else 5)
            for p in members:
                ax.annotate(p.mode.split("+", 1)[-1] if "+" in p.mode and not p.mode.startswith("coarse") else p.mode, (p.ms, p.mean_aee), fontsize=6,
                            xytext=(3, 3), textcoords="offset points")
        shown = [p.mean_aee for p in rows if p.mode != "zero"]
        zero = next((p for p in rows if p.mode == "zero"), None)
        top = 1.15 * max(shown) if shown else None
        if zero and top and zero.mean_aee <= top:
            ax.axhline(zero.mean_aee, color="grey", ls="--", lw=0.8, label="zero flow")
        if top:
            ax.set_ylim(0, top)
        ref = next((p for p in rows if p.mode == reference), None)
        if ref:
            ax.axvline(ref.ms / 5, color="tab:red", ls=":", lw=0.8, label=f"1/5 of {reference}'s time")
            ax.axhline(ref.mean_aee, color="tab:red", ls="-", lw=0.5, alpha=0.5, label=f"{reference}'s AEE")
        ax.set_xscale("log")
        ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())  # the decades only: no crowded labels
        ax.set_xlabel("ms per window (log)")
        ax.set_ylabel("AEE (px)")
        title = f"{data}, dt = {dt}" + (f" (zero flow: {zero.mean_aee:.2f})" if zero else "")
        ax.set_title(title, fontsize=9)
    axes[0][0].legend(fontsize=7, loc="lower left")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = temporary_path(path)
    fig.savefig(tmp, dpi=90, format="png")
    os.replace(tmp, path)
    plt.close(fig)
    return path


def load_points(path: str | os.PathLike) -> list[Point]:
    """The points a run wrote (``tradeoff.json``), to plot or tabulate again."""
    rows = json.loads(Path(path).read_text())
    points = []
    for r in rows:
        p = Point(r["data"], r["dt"], r["mode"], list(r["aee_per_sequence"]), list(r.get("hmc_per_sequence", [])),
                  list(r.get("hmc_zero_per_sequence", [])), windows=r.get("windows", 0))
        p.ms_sum, p.ms_count = (float(r["ms"]), 1) if r.get("ms") is not None and math.isfinite(r["ms"]) else (0.0, 0)
        points.append(p)
    return points


def points_json(points: list[Point]) -> str:
    return json.dumps([p.as_dict() for p in points], indent=1) + "\n"


def write_json(points: list[Point], path: Path) -> None:
    """The points as JSON, written to a temporary and renamed (never through a planted link)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = temporary_path(path)
    tmp.write_text(points_json(points))
    os.replace(tmp, path)
