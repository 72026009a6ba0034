"""Evaluating a flow policy (or zero flow) on recordings through the EventFlow env.

Each sequence is rolled from its first window to its last with the recurrent state carried
across windows and reset between sequences. Per window: AEE and outlier % against the ground
truth where there is one (docs/method.md, "Metrics": pixels with valid ground truth and at least one
event; the prediction scaled by ``dt_ratio`` when the input window differs from the
ground-truth interval), L_HMC of the prediction as the env's reward scores it (the env's -reward:
``losses.window_loss``, border rule included) and of zero flow, FWL and RSAT. Per sequence:
the means over its windows (windows without events or ground truth are left out of the means
they cannot contribute to).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np
import torch
from tqdm import tqdm

from envs.dataset import resolve_data
from envs.env import EventFlowEnv, NoWindowsError
from envs.representations import event_mask
from envs.visualize import count_image_to_rgb, flow_legend, flow_to_rgb, panel, save_animation, save_png
from envs.windows import FALLBACK_INTERVAL_US, Window, window_grid
from losses import EventBatch, flow_error, fwl, rsat, sample_flow, warped_event_images, window_loss, zero_flow_loss

from .policy import FlowPolicy, ZeroFlowPolicy
from .rollout import WindowStep, observation_options, rollout

__all__ = ["TABLE_LEGEND", "SequenceResult", "evaluate", "env_loss", "results_table", "results_json", "window_panel",
           "first_window_panel", "windowing_of"]

METRICS = ("aee", "outlier_pct", "cosine", "hmc", "hmc_zero", "fwl", "rsat", "ms")


def flow_cosine(flow: np.ndarray, flow_gt: np.ndarray, mask: np.ndarray) -> float:
    """Mean cosine between predicted and true flow vectors over ``mask`` pixels where both are
    non-zero: 1 = right directions everywhere, ~0 = unrelated (e.g. a constant flow on varied
    motion). NaN when no pixel qualifies."""
    a, b = flow[:, mask].astype(np.float64), flow_gt[:, mask].astype(np.float64)
    na, nb = np.hypot(*a), np.hypot(*b)
    ok = (na > 1e-6) & (nb > 1e-6)
    if not ok.any():
        return float("nan")
    return float(np.mean((a[:, ok] * b[:, ok]).sum(0) / (na[ok] * nb[ok])))


@dataclass
class SequenceResult:
    name: str
    size: tuple = ()  # (H, W) of the frame it was evaluated in
    windowing: str = ""  # how its windows were cut
    windows: int = 0
    sums: dict = field(default_factory=lambda: {k: 0.0 for k in METRICS})
    counts: dict = field(default_factory=lambda: {k: 0 for k in METRICS})

    def add(self, key: str, value: float) -> None:
        if value is not None and math.isfinite(value):  # a protocol's own metrics (e.g. DSEC's 1PE) join METRICS
            self.sums[key] = self.sums.get(key, 0.0) + float(value)
            self.counts[key] = self.counts.get(key, 0) + 1

    def mean(self, key: str) -> float:
        return self.sums[key] / self.counts[key] if self.counts.get(key) else float("nan")

    def keys(self) -> list[str]:
        """METRICS, then any further metric a scorer added."""
        return list(METRICS) + [k for k in self.sums if k not in METRICS]

    def as_dict(self) -> dict[str, Any]:
        return {"sequence": self.name, "windows": self.windows, "size": list(self.size), "windowing": self.windowing,
                **{k: self.mean(k) for k in self.keys()}}


def _iwe_picture(flow: np.ndarray, window: Window, size) -> np.ndarray:
    """Image of warped events at s = 1 (both polarities), as RGB."""
    b = EventBatch.from_windows([window])
    with torch.no_grad():
        u = sample_flow(torch.from_numpy(flow)[None], b.x, b.y)
        count, _ = warped_event_images(b, u, size[0], size[1], references=(1.0,))
    return count_image_to_rgb(count[0, 0].numpy())


def _describe_windows(window: str, size: int, grid_kind: str | None) -> str:
    """How the windows were cut, for table titles and JSON."""
    if window == "frames":
        what = {"ground truth": "ground-truth intervals", "frames": "APS frame intervals",
                "time": f"fixed {FALLBACK_INTERVAL_US} us intervals (no ground truth, no frames)"}[grid_kind]
        return f"{size} x {what}"
    return f"{size} us" if window == "time" else f"{size} events"


def evaluate(
    policy: FlowPolicy | None,
    data,
    *,
    window: str = "frames",
    window_size: int | None = None,
    crop=None,
    dt_ratio: float = 1.0,
    max_windows: int | None = None,
    pictures_dir: str | Path | None = None,
    pictures_per_sequence: int = 2,
    animation_windows: int = 0,
    progress: bool = True,
    flow_scaling: float | None = None,
    data_format: str | None = None,
    data_options: dict | None = None,
    windows_fn: Callable | None = None,
    scorer_fn: Callable | None = None,
    flow_sink: Callable | None = None,
    shard: tuple[int, int] = (0, 1),
    measures: Sequence[str] = ("loss", "fwl", "rsat"),
) -> list[SequenceResult]:
    """Roll ``policy`` through every sequence of ``data``, each at its own sensor size.

    policy: any flow policy (``agents.policy.FlowPolicy``: a :class:`RecurrentPolicy`, a policy
    that solves each window from its events such as ``agents.cmax.ContrastMaximisationPolicy``,
    a wrapper of ``agents.wrappers``, a plug-in's ``act(obs)``), or None (zero flow); rolled
    through each sequence by ``agents.rollout.rollout``.
    Every recording is evaluated whole in its own sensor frame (the built-in networks pad the
    input to a multiple of 16 and crop their flow back), unless ``crop`` is given: then that
    crop of every recording (``(h, w)`` centred, or ``(top, left, h, w)``).
    window, window_size: as in :class:`EventFlowEnv`; ``frames`` windows follow the ground-truth
    grid, else the APS frames, else fixed 30 Hz intervals (``envs.windows.window_grid``).
    dt_ratio: ground-truth interval / input window duration; predictions are multiplied by
    it before the comparison with ground truth (linear motion). max_windows: per sequence.
    pictures_dir: where to write one labelled PNG panel per drawn window (count image,
    predicted flow, ground truth, warped events with zero and predicted flow, colour-wheel
    legend; AEE / FWL in the caption) for the first ``pictures_per_sequence`` windows, and, with
    ``animation_windows > 0``, a GIF per sequence of count image + predicted flow over its first
    that many windows.
    data_format, data_options: reader choice and options (see EventFlowEnv).
    windows_fn: reader -> (K, 2) µs ``[t_start, t_end)`` rows, the windows to evaluate (an
    evaluation protocol's valid range); default: all windows of the chosen mode.
    scorer_fn: reader -> score, a benchmark's scoring of that recording (``agents.benchmarks``):
    ``score(flow, info, window, size, dt_ratio) -> (metrics, mask)`` (window: ``info["window"]``)
    with metrics a dict of floats
    ("aee" and any others, plus "n_pixels") and mask the (H, W) bool pixels scored; it replaces
    the default AEE / outlier % over pixels with events and valid ground truth, and is also
    called on windows without events. flow_sink: ``(reader, window, flow)`` called with every
    window's predicted flow (window: ``info["window"]``, its bounds and events), e.g. a benchmark
    submission writer. L_HMC is the env's reward: ``window_loss`` with the env's loss spec and
    ``flow_scaling`` (the border rule included).
    Per window the time the policy takes to produce its flow is measured (``ms``).
    shard: (rank, world): only sequences rank, rank + world, rank + 2 world, ... (the share of one
    process of a distributed run, which adds the results of all).
    measures: which of the measures beside AEE, outlier % and cosine (always taken where there is
    ground truth) to take: "loss" (L_HMC and zero flow's), "fwl", "rsat"; a training run's
    validation takes fewer (each costs about as much as the AEE's whole window).
    """
    unknown = set(measures) - {"loss", "fwl", "rsat"}
    if unknown:
        raise ValueError(f"measures: unknown {sorted(unknown)}; known: loss, fwl, rsat")
    rank, world = shard
    if not 0 <= rank < world:
        raise ValueError(f"shard must be (rank, world) with 0 <= rank < world, got {shard}")
    policy = ZeroFlowPolicy() if policy is None else policy
    sources = resolve_data(data, format=data_format, options=data_options)
    results = []
    total = len(sources)
    for index in range(rank, total, world):
        # one env per recording: each in its own frame, nothing cropped unless asked
        env = EventFlowEnv(data, window=window, window_size=window_size, crop=crop, compute_reward=False,
                           flow_scaling=flow_scaling, data_format=data_format, data_options=data_options,
                           sequences=[index], **observation_options(policy))
        try:
            results.append(_evaluate_sequence(
                env, policy, index, total, window=window, windows_fn=windows_fn, dt_ratio=dt_ratio,
                max_windows=max_windows, pictures_dir=pictures_dir, pictures_per_sequence=pictures_per_sequence,
                animation_windows=animation_windows, progress=progress, scorer_fn=scorer_fn, flow_sink=flow_sink,
                measures=frozenset(measures)))
        finally:
            env.close()
    return results


def _evaluate_sequence(env: EventFlowEnv, policy: FlowPolicy, index: int, total: int, *, window, windows_fn,
                       dt_ratio, max_windows, pictures_dir, pictures_per_sequence, animation_windows, progress,
                       scorer_fn=None, flow_sink=None, measures=frozenset(("loss", "fwl", "rsat"))) -> SequenceResult:
    size = (env.height, env.width)
    reader = env.sources[0].reader()
    options: dict[str, Any] = {"sequence": 0}
    grid_kind = window_grid(reader)[1] if window == "frames" else None
    if windows_fn is not None:
        options["windows"] = windows_fn(reader)
    score = scorer_fn(reader) if scorer_fn is not None else None
    described = _describe_windows(window, env.window_size, grid_kind)
    result = SequenceResult(env.sequence_names[0], size=size, windowing=described)
    try:
        steps = rollout(policy, env, options=options, max_windows=max_windows)
    except NoWindowsError:  # too short for this window size: reported with 0 windows
        return result
    bar = tqdm(desc=f"eval {result.name} ({index + 1}/{total})", unit="win", disable=not progress, leave=False)
    frames: list[np.ndarray] = []
    for step in steps:
        if step.index:  # a sequence's first window pays for warm-up (kernel compilation, allocations)
            result.add("ms", 1e3 * step.seconds)
        if flow_sink is not None:
            flow_sink(reader, step.window, step.flow)
        aee = _score_window(result, env, step, score, dt_ratio, measures)
        if pictures_dir is not None and step.index < pictures_per_sequence and len(step.window.events):
            path = Path(pictures_dir) / f"{result.name}_w{step.index:03d}.png"
            save_png(path, window_panel(step.obs["count_image"], step.flow, step.window, step.info.get("flow_gt"),
                                        aee=aee))
        if pictures_dir is not None and step.index < animation_windows:
            frames.append(_animation_frame(step))
        result.windows += 1
        bar.update(1)
    bar.close()
    if frames:
        save_animation(Path(pictures_dir) / f"{result.name}.gif", frames, fps=10)
    return result


def _score_window(result: SequenceResult, env: EventFlowEnv, step: WindowStep, score, dt_ratio: float,
                  measures=frozenset(("loss", "fwl", "rsat"))) -> float | None:
    """Add one window's metrics to ``result`` (module docstring; ``measures`` as in
    :func:`evaluate`); returns its AEE (None: not scored)."""
    flow, win, info, size = step.flow, step.window, step.info, (env.height, env.width)
    n_events = len(win.events)
    if n_events:
        if "loss" in measures:
            for key, value in env_loss(env, flow, win).items():
                result.add(key, value)
        if "fwl" in measures:
            result.add("fwl", fwl(flow, win, size))
        if "rsat" in measures:
            result.add("rsat", rsat(flow, win, size))
    if "flow_gt" not in info or not (n_events or score is not None):
        return None
    if score is None:
        scored = event_mask(win.events, size)
        err = flow_error(flow, info["flow_gt"], info["flow_gt_valid"], scored, dt_ratio=dt_ratio)
        scored = scored & info["flow_gt_valid"]
    else:
        err, scored = score(flow, info, win, size, dt_ratio)
    if err["n_pixels"] == 0:
        return None
    for key, value in err.items():
        if key != "n_pixels":
            result.add(key, value)
    result.add("cosine", flow_cosine(flow, info["flow_gt"], scored))
    return err["aee"]


def _animation_frame(step: WindowStep) -> np.ndarray:
    """One frame of a sequence's GIF: count image and predicted flow (the ground truth's scale)."""
    scale = float(np.abs(step.info["flow_gt"]).max()) if "flow_gt" in step.info else None
    return panel([("events", count_image_to_rgb(step.obs["count_image"])), ("flow", flow_to_rgb(step.flow, scale))],
                 caption=f"window {step.index}")


def env_loss(env: EventFlowEnv, flow: np.ndarray, window: Window) -> dict[str, float]:
    """``{"hmc": .., "hmc_zero": ..}``: the window's loss under ``flow`` as ``env`` rewards it (its
    loss spec and flow scaling, border rule included: the env's -reward for that action) and
    under zero flow. flow: (2, H, W) float32 pixels over the window."""
    action = torch.from_numpy(np.asarray(flow, np.float32))[None]
    zero = zero_flow_loss(action, window, env.loss_spec, flow_scaling=env.flow_scaling).per_sample
    with torch.no_grad():
        loss = window_loss(action, window, env.loss_spec, flow_scaling=env.flow_scaling, zero_flow=zero)
    return {"hmc": float(loss.loss), "hmc_zero": float(zero[0])}


def window_panel(count: np.ndarray, flow: np.ndarray, window: Window, flow_gt: np.ndarray | None = None,
                 aee: float | None = None) -> np.ndarray:
    """One labelled picture of a window: count image, predicted flow, ground truth (if any),
    warped events with zero and with the predicted flow, a colour-wheel legend; the caption
    gives the window's AEE (if any) and FWL. Flows share one colour scale (the ground truth's
    largest magnitude, else the prediction's), which the legend's rim shows."""
    size = tuple(flow.shape[-2:])
    scale = float(np.abs(flow_gt).max()) if flow_gt is not None else float(np.hypot(*flow).max())
    scale = max(scale, 1e-3)
    tiles = [("events", count_image_to_rgb(count)), ("predicted flow", flow_to_rgb(flow, scale))]
    if flow_gt is not None:
        tiles.append(("ground truth", flow_to_rgb(flow_gt, scale)))
    tiles += [("warped, zero flow", _iwe_picture(np.zeros_like(flow), window, size)),
              ("warped, predicted", _iwe_picture(flow, window, size)),
              (f"colours: rim {scale:.1f} px", flow_legend(min(64, max(size))))]
    caption = f"{window.t_start}-{window.t_end} us   FWL {fwl(flow, window, size):.3f}"
    if aee is not None:
        caption += f"   AEE {aee:.3f} px"
    return panel(tiles, caption)


def first_window_panel(policy: FlowPolicy | None, data, *, crop=None, flow_scaling: float | None = None,
                       data_format: str | None = None, data_options: dict | None = None,
                       max_windows: int = 50) -> np.ndarray | None:
    """:func:`window_panel` of the first window with events of the first sequence of ``data``
    (``frames`` windows, the policy rolled from a fresh state; None: zero flow): events, predicted
    flow with the colour wheel, ground truth where present. None when none of its first
    ``max_windows`` windows holds events. Returns (H, W, 3) uint8."""
    policy = ZeroFlowPolicy() if policy is None else policy
    env = EventFlowEnv(data, window="frames", crop=crop, compute_reward=False, flow_scaling=flow_scaling,
                       data_format=data_format, data_options=data_options, sequences=[0],
                       **observation_options(policy))
    try:
        for step in rollout(policy, env, options={"sequence": 0}, max_windows=max_windows):
            if len(step.window.events):
                return window_panel(step.obs["count_image"], step.flow, step.window, step.info.get("flow_gt"))
    except NoWindowsError:
        pass
    finally:
        env.close()
    return None


def _fmt(value: float, digits: int = 3) -> str:
    return "-" if value is None or not math.isfinite(value) else f"{value:.{digits}f}"


def results_table(named_results: dict[str, list[SequenceResult]], title: str = "",
                  per_sequence: bool | None = None) -> str:
    """Markdown table, paper layout: one row per method; per sequence AEE / outlier % and the
    number of windows the AEE averages (with ``per_sequence``; default when there are at most 6
    sequences), then the mean of the sequences' AEE, the cosine, L_HMC (the env's -reward,
    border rule included: :func:`env_loss`) and zero flow's over all windows, in how many
    sequences the method's L_HMC is below zero flow's, FWL, RSAT and the milliseconds per window
    (each sequence's first window, which pays for warm-up, not counted). Only the columns that hold a
    value are shown: without ground truth, no AEE, % outliers or cosine columns."""
    methods = list(named_results)
    sequences = [r.name for r in named_results[methods[0]]]
    per_sequence = len(sequences) <= 6 if per_sequence is None else per_sequence
    head = ["method"] + ([f"{s} AEE / %Out (windows)" for s in sequences] if per_sequence else [])
    head += ["mean AEE", "cos", "L_HMC", "L_HMC zero", "seq. L_HMC < zero", "FWL", "RSAT", "ms/win"]
    body = []  # a row's cells; None: no value
    for method in methods:
        rows = named_results[method]
        cells: list[str | None] = [method]
        if per_sequence:
            cells += [f"{_fmt(r.mean('aee'), 2)} / {_fmt(r.mean('outlier_pct'), 2)} ({r.counts['aee']})"
                      if r.counts.get("aee") else None for r in rows]
        pooled = {k: _pooled(rows, k) for k in METRICS}
        aees = [r.mean("aee") for r in rows if math.isfinite(r.mean("aee"))]
        scored = [r for r in rows if r.counts["hmc"]]
        below = sum(r.mean("hmc") < r.mean("hmc_zero") for r in scored)
        cells += [_cell(float(np.mean(aees)) if aees else float("nan"), 3), _cell(pooled["cosine"], 3)]
        cells += [_cell(pooled["hmc"], 4), _cell(pooled["hmc_zero"], 4), f"{below}/{len(scored)}" if scored else None,
                  _cell(pooled["fwl"], 4), _cell(pooled["rsat"], 4), _cell(pooled["ms"], 1)]
        body.append(cells)
    shown = [i for i in range(len(head)) if i == 0 or any(cells[i] is not None for cells in body)]
    lines = ([f"**{title}**", ""] if title else []) + ["| " + " | ".join(head[i] for i in shown) + " |",
                                                       "|" + "---|" * len(shown)]
    lines += ["| " + " | ".join("-" if cells[i] is None else cells[i] for i in shown) + " |" for cells in body]
    return "\n".join(lines)


def _cell(value: float, digits: int) -> str | None:
    """A table cell: the value, or None where there is none (NaN)."""
    return None if value is None or not math.isfinite(value) else f"{value:.{digits}f}"


def windowing_of(named_results: dict[str, list[SequenceResult]]) -> str:
    """The windowing of the evaluated sequences and how many windows the table holds, e.g. "1 x
    ground-truth intervals: 33 windows of 11 sequences" (several kinds joined with "; " and the
    number of sequences of each)."""
    rows = next(iter(named_results.values()))
    kinds: dict[str, int] = {}
    for r in rows:
        kinds[r.windowing] = kinds.get(r.windowing, 0) + 1
    count = f"{sum(r.windows for r in rows)} windows of {len(rows)} sequence{'s' if len(rows) != 1 else ''}"
    if len(kinds) == 1:
        return f"{next(iter(kinds))}: {count}"
    return "; ".join(f"{k} ({n} sequences)" for k, n in kinds.items()) + f": {count}"


#: What the columns of :func:`results_table` mean (printed under evaluate.py's tables).
TABLE_LEGEND = """Columns: AEE, the average endpoint error against the ground truth (pixels per window; mean over the
sequences' means), with %Out the share of pixels off by more than 3 px and 5 %; cos, the mean cosine between the
flow and the truth; L_HMC, the env's loss (the negative reward: the hybrid motion-compensation loss with the border
rule; lower is better), beside zero flow's on the same windows and in how many sequences the method's is below zero
flow's; FWL, the flow warp loss (the variance of the image of warped events over that of the unwarped ones; above
1 is sharper than zero flow); RSAT, the ratio of squared average timestamps (below 1 is better than zero flow);
ms/win, milliseconds per window (each sequence's first window left out). Only columns with a value are shown."""


def _pooled(rows: list[SequenceResult], key: str) -> float:
    total = sum(r.counts.get(key, 0) for r in rows)
    return sum(r.sums.get(key, 0.0) for r in rows) / total if total else float("nan")


def _clean(value):
    return None if isinstance(value, float) and not math.isfinite(value) else value


def _metrics(rows: list[SequenceResult]) -> dict:
    """Metrics pooled over the windows of ``rows`` (one row: that sequence's means)."""
    keys = list(dict.fromkeys(k for r in rows for k in r.keys())) if rows else list(METRICS)
    out = {key: _clean(_pooled(rows, key)) for key in keys}
    out["windows"] = sum(r.windows for r in rows)
    return out


def results_json(per_dt: dict[str, dict[str, list[SequenceResult]]]) -> str:
    """JSON of evaluations at several window settings.

    per_dt: {"dt1": {method: rows}, "dt4": {...}} (keys are free). The first method is the
    primary one: its results sit at the top level, the others under "baselines":

        {"method": name,
         "sequences": {seq: {"dt1": {aee, outlier_pct, hmc, hmc_zero, fwl, rsat, windows}, "dt4": {...},
                             "fwl": .., "rsat": ..}},      # fwl / rsat of the first key
         "overall": {"dt1": {...}, "dt4": {...}, "fwl": .., "rsat": ..},
         "baselines": {name: {"sequences": ..., "overall": ...}}}

    A metric without data in every entry (AEE, % outliers and cosine without ground truth) is
    left out, as the table leaves out its column; one without data in some entries is null there.
    """
    keys = list(per_dt)
    methods = list(per_dt[keys[0]])

    def block(method: str) -> dict:
        sequences: dict = {}
        overall: dict = {}
        for key in keys:
            rows = per_dt[key][method]
            for r in rows:
                sequences.setdefault(r.name, {})[key] = _metrics([r])
            overall[key] = _metrics(rows)
        for entry in list(sequences.values()) + [overall]:
            first = entry.get(keys[0], {})
            entry["fwl"], entry["rsat"] = first.get("fwl"), first.get("rsat")
        return {"sequences": sequences, "overall": overall}

    out = {"method": methods[0], **block(methods[0])}
    out["baselines"] = {m: block(m) for m in methods[1:]}
    _drop_empty_metrics([out] + list(out["baselines"].values()), keys)
    return json.dumps(out, indent=2)


def _drop_empty_metrics(blocks: list[dict], keys: list[str]) -> None:
    """Remove, from every metrics dict of ``blocks`` (and the fwl / rsat beside them), the
    metrics that are null in all of them."""
    entries = [entry for b in blocks for entry in list(b["sequences"].values()) + [b["overall"]]]
    metrics = [entry[key] for entry in entries for key in keys if key in entry] + entries
    names = {name for m in metrics for name in m if name != "windows" and not isinstance(m[name], dict)}
    for name in names:
        if all(m.get(name) is None for m in metrics if name in m):
            for m in metrics:
                m.pop(name, None)
