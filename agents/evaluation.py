"""Evaluating a flow policy (or zero flow) on recordings through the EventFlow env.

Each sequence is rolled from its first window to its last with the recurrent state carried
across windows and reset between sequences. Per window: AEE and outlier % against the ground
truth where there is one (REFERENCE section 7: pixels with valid ground truth and at least one
event; the prediction scaled by ``dt_ratio`` when the input window differs from the
ground-truth interval), L_HMC of the prediction and of zero flow, FWL and RSAT. Per sequence:
the means over its windows (windows without events or ground truth are left out of the means
they cannot contribute to).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np
import torch
from tqdm import tqdm

from envs.env import EventFlowEnv, NoWindowsError
from envs.representations import event_mask
from envs.visualize import count_image_to_rgb, flow_to_rgb, save_png
from envs.windows import window_bounds
from losses import EventBatch, flow_error, fwl, hmc_loss, rsat, sample_flow, warped_event_images

from .policy import RecurrentPolicy

__all__ = ["SequenceResult", "evaluate", "results_table", "results_json"]

METRICS = ("aee", "outlier_pct", "cosine", "hmc", "hmc_zero", "fwl", "rsat")


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
    windows: int = 0
    sums: dict = field(default_factory=lambda: {k: 0.0 for k in METRICS})
    counts: dict = field(default_factory=lambda: {k: 0 for k in METRICS})

    def add(self, key: str, value: float) -> None:
        if value is not None and math.isfinite(value):
            self.sums[key] += float(value)
            self.counts[key] += 1

    def mean(self, key: str) -> float:
        return self.sums[key] / self.counts[key] if self.counts[key] else float("nan")

    def as_dict(self) -> dict[str, Any]:
        return {"sequence": self.name, "windows": self.windows, **{k: self.mean(k) for k in METRICS}}


class _EventView:
    def __init__(self, events):
        self.x, self.y, self.p = events["x"], events["y"], events["p"]


def _iwe_picture(flow: np.ndarray, window: dict, size) -> np.ndarray:
    """Image of warped events at s = 1 (both polarities), as RGB."""
    b = EventBatch.from_windows([window])
    with torch.no_grad():
        u = sample_flow(torch.from_numpy(flow)[None], b.x, b.y)
        count, _ = warped_event_images(b.x, b.y, b.tau, b.p, b.mask, u, size[0], size[1], references=(1.0,))
    return count_image_to_rgb(count[0, 0].numpy())


def evaluate(
    policy: RecurrentPolicy | None,
    data,
    *,
    window: str = "frames",
    window_size: int | None = None,
    crop=None,
    dt_ratio: float = 1.0,
    max_windows: int | None = None,
    pictures_dir: str | Path | None = None,
    pictures_per_sequence: int = 2,
    progress: bool = True,
    flow_scaling: float | None = None,
    data_format: str | None = None,
    data_options: dict | None = None,
    windows_fn: Callable | None = None,
    no_gt_window_us: int = 33_333,
) -> list[SequenceResult]:
    """Roll ``policy`` (None: zero flow) through every sequence of ``data``.

    dt_ratio: ground-truth interval / input window duration; predictions are multiplied by
    it before the comparison with ground truth (linear motion). max_windows: per sequence.
    pictures_dir: where to write PNGs (count image, predicted flow, ground truth, images of
    warped events with zero and predicted flow) for the first windows of each sequence.
    data_format, data_options: reader choice and options (see EventFlowEnv).
    windows_fn: reader -> (K, 2) µs ``[t_start, t_end)`` rows, the windows to evaluate (an
    evaluation protocol's valid range); default: all windows of the chosen mode.
    no_gt_window_us: in ``frames`` mode, a recording without a ground-truth grid is cut into
    time windows of this length instead (FWL, RSAT and L_HMC only; AEE is reported as NaN).
    """
    parts = ("count_image",) if policy is None or policy.input_key == "count_image" else ("count_image", policy.input_key)
    env = EventFlowEnv(data, window=window, window_size=window_size, crop=crop, compute_reward=False,
                       flow_scaling=flow_scaling, data_format=data_format, data_options=data_options,
                       observations=parts, voxel_bins=policy.voxel_bins if policy is not None else 5)
    size = (env.height, env.width)
    results = []
    total = len(env.sources)
    for index in range(total):
        options = {"sequence": index}
        reader = env.sources[index].reader()
        if windows_fn is not None:
            options["windows"] = windows_fn(reader)
        elif window == "frames" and reader.flow_timestamps() is None:
            options["windows"] = window_bounds(reader, "time", no_gt_window_us)[:, :2]
        try:
            obs, info = env.reset(options=options)
        except NoWindowsError:  # too short for this window size: reported with 0 windows
            results.append(SequenceResult(env.sequence_names[index]))
            continue
        if policy is not None:
            policy.reset()
        result = SequenceResult(info["sequence"])
        bar = tqdm(desc=f"eval {info['sequence']} ({index + 1}/{total})", unit="win", disable=not progress, leave=False)
        truncated = False
        while not truncated and (max_windows is None or result.windows < max_windows):
            flow = np.zeros((2,) + size, np.float32) if policy is None else policy.act(obs)
            win = {**info["events"], "t_start": info["t_start"], "t_end": info["t_end"]}
            n_events = len(win["t"])
            if n_events:
                batch = EventBatch.from_windows([win])
                with torch.no_grad():
                    for key, f in (("hmc", flow), ("hmc_zero", np.zeros_like(flow))):
                        result.add(key, float(hmc_loss(torch.from_numpy(f)[None], batch, flow_scaling=env.flow_scaling).loss))
                result.add("fwl", fwl(flow, win, size))
                result.add("rsat", rsat(flow, win, size))
            if "flow_gt" in info and n_events:
                err = flow_error(flow, info["flow_gt"], info["flow_gt_valid"], event_mask(_EventView(win), size), dt_ratio=dt_ratio)
                if err["n_pixels"] > 0:
                    result.add("aee", err["aee"])
                    result.add("outlier_pct", err["outlier_pct"])
                    mask = event_mask(_EventView(win), size) & info["flow_gt_valid"]
                    result.add("cosine", flow_cosine(flow, info["flow_gt"], mask))
            if pictures_dir is not None and result.windows < pictures_per_sequence and n_events:
                stem = Path(pictures_dir) / f"{info['sequence']}_w{result.windows:03d}"
                save_png(f"{stem}_events.png", count_image_to_rgb(obs["count_image"]))
                scale = float(np.abs(info["flow_gt"]).max()) if "flow_gt" in info else None
                save_png(f"{stem}_flow.png", flow_to_rgb(flow, scale))
                if "flow_gt" in info:
                    save_png(f"{stem}_flow_gt.png", flow_to_rgb(info["flow_gt"], scale))
                save_png(f"{stem}_iwe_zero.png", _iwe_picture(np.zeros_like(flow), win, size))
                save_png(f"{stem}_iwe_pred.png", _iwe_picture(flow, win, size))
            result.windows += 1
            bar.update(1)
            obs, _, _, truncated, info = env.step(flow)
        bar.close()
        results.append(result)
    env.close()
    return results


def _fmt(value: float, digits: int = 3) -> str:
    return "-" if value is None or not math.isfinite(value) else f"{value:.{digits}f}"


def results_table(named_results: dict[str, list[SequenceResult]], title: str = "") -> str:
    """Markdown table, paper layout: one row per method, per sequence AEE / outlier %, then
    the mean L_HMC (and zero flow's), FWL and RSAT over all windows."""
    methods = list(named_results)
    sequences = [r.name for r in named_results[methods[0]]]
    head = ["method"] + [f"{s} AEE / %Out" for s in sequences] + ["mean AEE", "cos", "L_HMC", "L_HMC zero", "FWL", "RSAT"]
    lines = ([f"**{title}**", ""] if title else []) + ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for method in methods:
        rows = named_results[method]
        cells = [method] + [f"{_fmt(r.mean('aee'), 2)} / {_fmt(r.mean('outlier_pct'), 2)}" for r in rows]
        pooled = {k: _pooled(rows, k) for k in METRICS}
        aees = [r.mean("aee") for r in rows if math.isfinite(r.mean("aee"))]
        cells += [_fmt(float(np.mean(aees)) if aees else float("nan"), 3), _fmt(pooled["cosine"], 3)]
        cells += [_fmt(pooled["hmc"], 4), _fmt(pooled["hmc_zero"], 4), _fmt(pooled["fwl"], 4), _fmt(pooled["rsat"], 4)]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def _pooled(rows: list[SequenceResult], key: str) -> float:
    total = sum(r.counts[key] for r in rows)
    return sum(r.sums[key] for r in rows) / total if total else float("nan")


def _clean(value):
    return None if isinstance(value, float) and not math.isfinite(value) else value


def _metrics(rows: list[SequenceResult]) -> dict:
    """Metrics pooled over the windows of ``rows`` (one row: that sequence's means)."""
    out = {key: _clean(_pooled(rows, key)) for key in METRICS}
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

    Metrics without data (AEE where there is no ground truth) are null.
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
    return json.dumps(out, indent=2)
