"""Flow for a whole recording: a model run window by window, the flows written to an h5 file,
a preview animation and a summary of how well the flow explains the events.

The windows and observations are the env's (:class:`envs.env.EventFlowEnv`, as in
:func:`agents.evaluation.evaluate`): ground-truth aligned ``frames`` (a recording without a
ground-truth grid falls back to time windows of ``no_gt_window_us``), ``time`` or ``count``;
the recurrent state is carried from each window to the next. Per window the summary gathers
L_HMC of the prediction (the env's -reward, border rule included, as the evaluation's) and of
zero flow, FWL and RSAT (ratios against zero flow, so zero
flow scores 1 on both), and AEE / outlier % where the recording has ground truth.

Output h5 (``FLOW_FORMAT``), written under a temporary name and renamed when complete (an
interrupted run leaves nothing under the final name):

- ``flow``: (K, 2, H, W) float16, pixels of displacement over each window (x right, y down),
  gzip-compressed, one chunk per window;
- ``t_start``, ``t_end``: (K,) int64 µs, each window ``[t_start, t_end)``; ``num_events`` (K,);
- ``metrics/<name>``: (K,) float32 per-window hmc, hmc_zero, fwl, rsat, aee, outlier_pct (NaN
  where a window has no events or no ground truth);
- with ``per_event``: ``event_flow`` (N, 2) float16, the flow at each event's pixel, events in
  window order, and ``event_offsets`` (K + 1,) int64: window k's rows are
  ``event_offsets[k]:event_offsets[k+1]``;
- attributes: ``format``, ``sensor_size`` (H, W of the flow frame), ``crop`` (its place in the
  recording's sensor), ``recording``, ``reader``, ``window`` and ``window_size`` (the mode and
  size that cut the windows: "time" when frames fell back for want of ground truth), ``model`` (JSON
  provenance), ``split`` (sub-windows the network stepped through per window, 1: none), ``units``.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import h5py
import numpy as np
from tqdm import tqdm

from agents.evaluation import env_loss
from agents.policy import FlowPolicy, RecurrentPolicy
from agents.rollout import WindowStep, observation_options, rollout
from agents.wrappers.subwindows import SubWindowPolicy
from envs.env import EventFlowEnv
from envs.outputs import Output
from envs.representations import event_mask
from envs.visualize import (
    animation_path,
    count_image_to_rgb,
    flow_arrows,
    flow_legend,
    flow_to_rgb,
    panel,
    save_animation,
)
from envs.windows import FALLBACK_INTERVAL_US, WINDOW_MODES, Window, check_window_fits, window_bounds
from losses import flow_error, fwl, rsat

__all__ = ["FLOW_FORMAT", "PredictResult", "load_policy", "predict", "summary_table"]

FLOW_FORMAT = "evflow-flow"
WindowMode = Literal["frames", "time", "count"]
PER_WINDOW = ("hmc", "hmc_zero", "fwl", "rsat", "aee", "outlier_pct", "aee_zero")


@dataclass
class PredictResult:
    """What :func:`predict` wrote and measured.

    per_window: {metric: (K,) float64} (NaN where not defined or not scored); seconds: wall time
    of the loop; stages: its seconds by stage ("input": reading the window and building the
    network's input, "flow": the policy, finish included, "metrics", "writing", "preview").
    """

    path: Path
    video: Path | None
    windows: int
    events: int
    seconds: float
    per_window: dict[str, np.ndarray] = field(default_factory=dict)
    stages: dict[str, float] = field(default_factory=dict)

    @property
    def scored(self) -> int:
        """How many windows the metrics were taken on."""
        values = self.per_window.get("hmc")
        return 0 if values is None else int(np.isfinite(values).sum())

    def where_the_time_goes(self) -> str:
        """One line: milliseconds per window by stage (metrics per scored window too)."""
        n = max(self.windows, 1)
        parts = [f"{name} {1e3 * sec / n:.0f}" for name, sec in self.stages.items()]
        return f"ms per window: {', '.join(parts)} (of {1e3 * self.seconds / n:.0f})"

    def mean(self, key: str) -> float:
        values = self.per_window[key]
        values = values[np.isfinite(values)]
        return float(values.mean()) if len(values) else float("nan")

    @property
    def windows_per_second(self) -> float:
        return self.windows / self.seconds if self.seconds > 0 else float("nan")


def load_policy(model: str | None = None, *, device: str = "cpu", width: str | int = "cpu",
                plugin: str | None = None) -> tuple[RecurrentPolicy, dict]:
    """The policy and its provenance for ``model``:

    - None or a shipped name (``agents/weights``): ``RecurrentPolicy.from_pretrained``;
    - a path to a checkpoint file written by training: ``agents.checkpoint.load_model``;
    - a registry name or ``package.module:factory``: a fresh, untrained model of ``width``.

    plugin: the dotted path a checkpoint may name (a file alone may only name a registered model).
    """
    from agents.checkpoint import load_model
    from agents.pretrained import DEFAULT_PRETRAINED, list_pretrained, pretrained_info
    from agents.registry import make_model, width_kwargs

    if model is None or model in list_pretrained():
        name = model or DEFAULT_PRETRAINED
        info = pretrained_info(name)
        provenance = {"kind": "pretrained", "name": name, **{k: info[k] for k in ("command", "date", "data") if k in info}}
        if model is None:  # the default: say how it was chosen
            from agents.pretrained import default_choice

            choice = default_choice()
            provenance["default"] = {k: choice[k] for k in ("mode", "chosen_on", "date") if k in choice}
        return RecurrentPolicy.from_pretrained(name, device=device), provenance
    if os.path.isfile(model):
        net, payload = load_model(model, map_location=device, plugin=plugin)
        cfg = payload.get("config") or {}
        provenance = {"kind": "checkpoint", "path": os.path.abspath(model), "model_name": payload.get("model_name"),
                      "model_config": payload.get("model_config"), "step": payload.get("step")}
        policy = RecurrentPolicy(net, device=device, input_key=cfg.get("input", "count_image"), voxel_bins=cfg.get("voxel_bins", 5))
        return policy, provenance
    kwargs = width_kwargs(width)
    net = make_model(model, **kwargs).eval()
    return RecurrentPolicy(net, device=device), {"kind": "untrained", "name": model, **kwargs}


def _open_sequence(policy: FlowPolicy, recording, sequence: int | str, *, window, window_size, crop, data_format,
                   data_options) -> tuple[EventFlowEnv, int]:
    """The env over ``sequence`` of ``recording`` alone, with ``policy``'s inputs, and its index in
    that env (0): the other recordings of a folder or split may have other sensor sizes.
    ValueError naming the recording's sequences when there is none such."""
    from envs.dataset import resolve_data

    names = [source.name for source in resolve_data(str(recording), format=data_format, options=data_options)]
    if isinstance(sequence, str) and sequence not in names:
        raise ValueError(f"sequence {sequence!r} is not in {recording}; its sequences: {names}")
    index = names.index(sequence) if isinstance(sequence, str) else int(sequence)
    if not 0 <= index < len(names):
        raise ValueError(f"sequence {index} outside [0, {len(names)}) for {recording}")
    env = EventFlowEnv(str(recording), data_format=data_format, data_options=data_options, window=window,
                       window_size=window_size, crop=crop, compute_reward=False, sequences=[index],
                       **observation_options(policy))
    return env, 0


def _windows(env: EventFlowEnv, reader, recording, window: str, start_s, end_s,
             no_gt_window_us) -> tuple[np.ndarray, str, int]:
    """(K, 2) µs rows [t_start, t_end): the env's windows of the recording inside [start_s, end_s)
    (seconds from its start; None: its start / end); and the mode and size that cut them.
    ValueError when there is none."""
    start_us = None if start_s is None else reader.t_start + int(round(start_s * 1e6))
    end_us = None if end_s is None else reader.t_start + int(round(end_s * 1e6))
    mode, size = window, env.window_size
    if window == "frames" and reader.flow_timestamps() is None:
        mode, size = "time", no_gt_window_us
    try:
        check_window_fits(reader, mode, size)
    except ValueError as err:
        raise ValueError(f"{recording}: {err}") from None
    bounds = window_bounds(reader, mode, size, t_from=start_us)[:, :2]
    if end_us is not None:
        bounds = bounds[bounds[:, 1] <= end_us]
    if len(bounds) == 0:
        raise ValueError(f"{recording}: no {window} window of size {env.window_size} inside the span "
                         f"[{start_s or 0}, {end_s if end_s is not None else 'end'}) s from the recording's start")
    return bounds, mode, size


class _FlowFile:
    """The output h5 (module docstring), written window by window into an open ``h5py.File``."""

    def __init__(self, f: h5py.File, bounds: np.ndarray, size: tuple[int, int], *, per_event: bool,
                 compression: int) -> None:
        h, w = size
        self.f, self.per_event = f, per_event
        self.flow = f.create_dataset("flow", (len(bounds), 2, h, w), np.float16, chunks=(1, 2, h, w),
                                     compression="gzip", compression_opts=compression, shuffle=True)
        f.create_dataset("t_start", data=bounds[:, 0])
        f.create_dataset("t_end", data=bounds[:, 1])
        self.counts = np.zeros(len(bounds), np.int64)
        self.events = 0  # events written so far
        if per_event:
            self.event_flow = f.create_dataset("event_flow", (0, 2), np.float16, maxshape=(None, 2),
                                               chunks=(1 << 16, 2), compression="gzip", compression_opts=compression)

    def write(self, k: int, flow: np.ndarray, window: Window) -> None:
        """Window k's flow (2, H, W) pixels, and with ``per_event`` the flow at its events."""
        n = len(window.events)
        self.counts[k] = n
        self.flow[k] = flow.astype(np.float16)
        if self.per_event and n:
            rows = flow[:, window.events.y.astype(np.int64), window.events.x.astype(np.int64)].T.astype(np.float16)
            self.event_flow.resize((self.events + n, 2))
            self.event_flow[self.events:] = rows
        self.events += n

    def finish(self, per_window: dict[str, np.ndarray]) -> None:
        """The event counts (and offsets) and the per-window metrics, once every window is in."""
        self.f.create_dataset("num_events", data=self.counts)
        if self.per_event:
            self.f.create_dataset("event_offsets", data=np.concatenate([[0], np.cumsum(self.counts)]).astype(np.int64))
        for key, values in per_window.items():
            self.f.create_dataset(f"metrics/{key}", data=values.astype(np.float32))


#: the widest a preview tile is by default (a sensor wider than this is shown subsampled)
PREVIEW_WIDTH = 640


def _preview(item: dict, scale: float, t0: int, arrows: bool = False) -> np.ndarray:
    """One preview frame (an item of :class:`_Preview`): the events, the colour-coded flow, the
    same flow on the pixels with events only (where it can be read), the ground truth where the
    recording has it, and the colour wheel, whose rim is ``scale`` pixels in every frame; with
    ``arrows``, sparse arrows over the flow at the events. Times from the recording's start ``t0``."""
    count, flow, events = item["count"], item["flow"].astype(np.float32), item["events"]
    colours = flow_to_rgb(flow, scale)
    at_events = np.where(events[..., None], colours, np.uint8(255))
    if arrows:
        at_events = flow_arrows(at_events, flow, events, spacing=max(8, at_events.shape[1] // 16))
    tiles = [("events", count), ("flow", colours), ("flow at events", at_events)]
    if item.get("gt") is not None:
        truth = np.where(item["valid"][..., None], flow_to_rgb(item["gt"].astype(np.float32), scale), np.uint8(255))
        tiles.append(("ground truth", truth))
    tiles.append((f"rim {scale:.2f} px", flow_legend(min(64, max(count.shape[:2])))))
    return panel(tiles, preview_caption(item["t_start"], item["t_end"], t0))


def preview_caption(t_start: int, t_end: int, t0: int) -> str:
    """A preview frame's caption: the window in seconds from the recording's start ``t0`` (µs)."""
    return (f"{(t_start - t0) / 1e6:.3f}-{(t_end - t0) / 1e6:.3f} s from the recording's start; flow in pixels over "
            "the window, one colour scale for the whole preview")


class _Preview:
    """The preview: at most ``frames`` windows spread evenly over ``windows``, kept subsampled to
    at most ``width`` pixels wide while the run goes (a subsampled pixel holds events when any
    pixel it stands for does) and drawn at its end on one colour scale, ``flow_max`` pixels at
    the wheel's rim, by default the 99th percentile of the flow's magnitude at the events over
    all of them: a colour is the same speed in every frame."""

    def __init__(self, windows: int, frames: int, width: int | None, arrows: bool, t0: int,
                 flow_max: float | None = None) -> None:
        self.at = set(np.linspace(0, windows - 1, min(frames, windows)).astype(int).tolist())
        self.width, self.arrows, self.t0, self.flow_max = width or PREVIEW_WIDTH, arrows, t0, flow_max
        self.items: list[dict] = []

    def add(self, step: WindowStep) -> None:
        if step.index not in self.at:
            return
        count = step.obs["count_image"]
        s = max(1, math.ceil(count.shape[-1] / self.width))
        h, w = count.shape[-2:]
        padded = np.zeros((-(-h // s) * s, -(-w // s) * s), bool)
        padded[:h, :w] = count.sum(axis=0) > 0
        events = padded.reshape(padded.shape[0] // s, s, padded.shape[1] // s, s).any(axis=(1, 3))
        gt = step.window.flow_gt
        self.items.append({"count": count_image_to_rgb(count[:, ::s, ::s]),
                           "flow": step.flow[:, ::s, ::s].astype(np.float16),
                           "events": events, "gt": None if gt is None else gt[:, ::s, ::s].astype(np.float16),
                           "valid": None if gt is None else step.window.flow_gt_valid[::s, ::s],
                           "t_start": int(step.window.t_start), "t_end": int(step.window.t_end)})

    def scale(self) -> float:
        """The colour wheel's rim in pixels: ``flow_max``, or the 99th percentile of the flow's
        magnitude at the events of every kept window (1 px when there are none)."""
        if self.flow_max:
            return float(self.flow_max)
        at = [np.hypot(*item["flow"].astype(np.float32))[item["events"]] for item in self.items]
        magnitudes = np.concatenate(at) if at else np.zeros(0)
        return max(float(np.percentile(magnitudes, 99)) if magnitudes.size else 1.0, 1e-3)

    def frames(self):
        """The frames, drawn one at a time (each item is let go once drawn)."""
        scale = self.scale()
        while self.items:
            yield _preview(self.items.pop(0), scale, self.t0, self.arrows)


def predict(
    policy: FlowPolicy,
    recording: str | os.PathLike,
    out_path: str | os.PathLike,
    *,
    window: WindowMode = "frames",
    window_size: int | None = None,
    start_s: float | None = None,
    end_s: float | None = None,
    crop=None,
    sequence: int | str = 0,
    data_format: str | None = None,
    data_options: dict | None = None,
    per_event: bool = False,
    video: str | os.PathLike | None = None,
    video_fps: float = 10.0,
    video_frames: int = 150,
    video_width: int | None = None,
    video_arrows: bool = False,
    flow_max: float | None = None,
    provenance: dict | None = None,
    no_gt_window_us: int = FALLBACK_INTERVAL_US,
    progress: bool = True,
    compression: int = 4,
    overwrite: bool = False,
    split: int = 1,
    score_windows: int | None = 100,
) -> PredictResult:
    """Run ``policy`` over every window of ``recording`` and write the flows (module docstring).

    window, window_size: as in the env (frames: grid steps, default 1; time: µs, default 10 000;
    count: events, default 15 000). start_s, end_s: only windows inside [start_s, end_s), in
    seconds from the recording's start (None: its start / end). crop: as in the env. video: path of the preview
    (``.gif``, ``.png`` for an animated PNG, or ``.mp4`` where a codec is installed), None for
    none; at most ``video_frames`` windows spread evenly over the run, each tile the sensor's size
    up to ``video_width`` pixels wide (default 640): events, flow, flow at the events, the ground
    truth where there is one, and the colour wheel, its rim ``flow_max`` pixels in every frame
    (default: the 99th percentile of the flow's magnitude at the events over the frames shown);
    ``video_arrows``: sparse arrows over the flow at the events.
    sequence: which recording when ``recording`` names several (a folder, a synthetic split).
    overwrite: replace an existing ``out_path`` (refused otherwise, and always when it is the
    recording itself), as ``scripts/convert.py`` does.
    split: step the network through this many equal sub-windows of every window and compose
    their flows (``agents.wrappers.subwindows``; for windows longer than the network's usual step).
    policy: any flow policy (``agents.policy.FlowPolicy``), rolled by ``agents.rollout.rollout``.
    score_windows: the per-window metrics (L_HMC, zero flow's, FWL, RSAT, AEE) are taken on this
    many windows spread evenly over the run (None: every window; 0: none); on a large sensor they
    cost more than the network (``PredictResult.where_the_time_goes``).
    """
    _check_options(window, split)
    with contextlib.ExitStack() as claims:  # every output claimed before any work (envs.outputs)
        flow_out, video_out = _claim_outputs(claims, recording, out_path, video, overwrite)
        env, index = _open_sequence(policy, recording, sequence, window=window, window_size=window_size, crop=crop,
                                    data_format=data_format, data_options=data_options)
        try:
            reader = env.sources[index].reader()
            bounds, mode, size = _windows(env, reader, recording, window, start_s, end_s, no_gt_window_us)
            attributes = _file_attributes(recording, reader, (env.height, env.width), mode, size, provenance, split)
            preview = (_Preview(len(bounds), video_frames, video_width, video_arrows, reader.t_start, flow_max)
                       if video_out else None)
            scored = _spread(len(bounds), score_windows)
            result = _run(SubWindowPolicy(policy, int(split)), env, {"sequence": index, "windows": bounds}, flow_out,
                          attributes, per_event=per_event, compression=compression, progress=progress, preview=preview,
                          scored=scored)
        finally:  # an exception (KeyboardInterrupt included) discards the temporary: nothing under the final name
            env.close()
        if preview is not None and preview.items:
            began = time.perf_counter()
            result.video = save_animation(video_out.path, preview.frames(), video_fps)
            result.stages["preview"] += time.perf_counter() - began
            result.seconds += time.perf_counter() - began
        flow_out.commit()
        return result


def _spread(windows: int, count: int | None) -> set[int]:
    """``count`` window indices spread evenly over ``windows`` (None: all of them)."""
    if count is None or count >= windows:
        return set(range(windows))
    return set(np.linspace(0, windows - 1, count).round().astype(int).tolist()) if count > 0 else set()


def _check_options(window: str, split: int) -> None:
    """ValueError naming the option for a window mode or split that :func:`predict` cannot run."""
    if window not in WINDOW_MODES:
        raise ValueError(f"window must be one of {WINDOW_MODES}, got {window!r}")
    if int(split) < 1:
        raise ValueError(f"split must be a number of sub-windows >= 1, got {split}")


def _claim_outputs(claims: contextlib.ExitStack, recording, out_path, video, overwrite: bool
                   ) -> tuple[Output, Output | None]:
    """The flow file's and the preview's claims (``envs.outputs.Output``), held by ``claims``."""
    inputs = [("recording", recording)]
    flow_out = claims.enter_context(Output(out_path, inputs=inputs, overwrite=overwrite))
    video_out = None
    if video:
        video_out = claims.enter_context(Output(animation_path(video), inputs=inputs, overwrite=overwrite))
    return flow_out, video_out


def _file_attributes(recording, reader, sensor_size: tuple[int, int], mode: str, size: int, provenance: dict | None,
                     split: int) -> dict:
    """The output h5's attributes but ``crop`` (module docstring)."""
    return dict(format=FLOW_FORMAT, version=1, sensor_size=sensor_size,
                recording=str(Path(recording).resolve()) if Path(recording).exists() else str(recording),
                reader=type(reader).__name__, window=mode, window_size=size,
                model=json.dumps(provenance or {}, default=str), split=int(split),
                units="flow: pixels of displacement over the window, channel 0 = x (right), 1 = y (down)")


def _run(actor: FlowPolicy, env: EventFlowEnv, options: dict, flow_out: Output, attributes: dict, *, per_event: bool,
         compression: int, progress: bool, preview: _Preview | None, scored: set[int]) -> PredictResult:
    """Roll ``actor`` through the windows ``options`` give (``env.reset`` options), write their
    flows to ``flow_out``'s temporary file (with ``attributes``), score the windows of ``scored``
    and add the preview's frames. Returns the result, without its video, with the time by stage."""
    bounds = options["windows"]
    per_window = {key: np.full(len(bounds), np.nan) for key in PER_WINDOW}
    stages = dict.fromkeys(("input", "flow", "metrics", "writing", "preview"), 0.0)
    bar = tqdm(total=len(bounds), desc=f"predict {env.sequence_names[options['sequence']]}", unit="win",
               disable=not progress)
    t0 = time.perf_counter()
    try:
        with h5py.File(flow_out.temporary, "w") as f:
            f.attrs.update(attributes)
            flows = _FlowFile(f, bounds, (env.height, env.width), per_event=per_event, compression=compression)
            mark = time.perf_counter()
            for step in rollout(actor, env, options=options):
                now = time.perf_counter()  # the generator's time since the last step: the input, then the flow
                stages["flow"] += step.seconds
                stages["input"] += now - mark - step.seconds
                mark = now
                if step.index == 0:
                    f.attrs["crop"] = step.info["crop"]  # where the env's frame sits in the sensor
                mark = _timed(stages, "writing", mark, flows.write, step.index, step.flow, step.window)
                if step.index in scored:
                    mark = _timed(stages, "metrics", mark, _score_window, per_window, step, env)
                if preview is not None:
                    mark = _timed(stages, "preview", mark, preview.add, step)
                bar.update(1)
            flows.finish(per_window)
        seconds = time.perf_counter() - t0
    finally:
        bar.close()
    return PredictResult(flow_out.path, None, len(bounds), flows.events, seconds, per_window, stages)


def _timed(stages: dict, stage: str, since: float, fn, *args) -> float:
    """Call ``fn(*args)``, add the time since ``since`` to ``stages[stage]``; the time now."""
    fn(*args)
    now = time.perf_counter()
    stages[stage] += now - since
    return now


def _score_window(per_window: dict, step: WindowStep, env: EventFlowEnv) -> None:
    """The evaluation's per-window metrics (agents/evaluation.py), stored at the step's index."""
    k, flow, win = step.index, step.flow, step.window
    if not len(win.events):
        return
    size = win.sensor_size
    for key, value in env_loss(env, flow, win).items():
        per_window[key][k] = value
    per_window["fwl"][k] = fwl(flow, win, size)
    per_window["rsat"][k] = rsat(flow, win, size)
    if win.flow_gt is not None:
        mask = event_mask(win.events, size)
        err = flow_error(flow, win.flow_gt, win.flow_gt_valid, mask)
        if err["n_pixels"] > 0:
            per_window["aee"][k], per_window["outlier_pct"][k] = err["aee"], err["outlier_pct"]
            zero = flow_error(np.zeros_like(flow), win.flow_gt, win.flow_gt_valid, mask)
            per_window["aee_zero"][k] = zero["aee"]


def _fmt(value: float, digits: int = 4) -> str:
    return "-" if not math.isfinite(value) else f"{value:.{digits}f}"


def summary_table(result: PredictResult, name: str = "model") -> str:
    """Markdown: the model against zero flow, means over the windows with events (AEE over
    those with ground truth; its columns only where there is some). FWL and RSAT are ratios to
    zero flow, which scores 1 on both."""
    m = result.mean
    truth = math.isfinite(m("aee"))
    scored = f"{result.scored} of {result.windows}"
    lines = [
        "| | windows scored | L_HMC | FWL (higher better) | RSAT (lower better) |"
        + (" AEE | % outliers |" if truth else ""),
        "|---|---|---|---|---|" + ("---|---|" if truth else ""),
        f"| {name} | {scored} | {_fmt(m('hmc'))} | {_fmt(m('fwl'))} | {_fmt(m('rsat'))} |"
        + (f" {_fmt(m('aee'), 3)} | {_fmt(m('outlier_pct'), 2)} |" if truth else ""),
        f"| zero flow | {scored} | {_fmt(m('hmc_zero'))} | 1.0000 | 1.0000 |"
        + (f" {_fmt(m('aee_zero'), 3)} | - |" if truth else ""),
    ]
    return "\n".join(lines)


def summary_dict(result: PredictResult) -> dict[str, Any]:
    """The means of :func:`summary_table` as a JSON-ready dict (NaN -> None)."""
    clean = lambda v: v if math.isfinite(v) else None  # noqa: E731
    return {"windows": result.windows, "windows_scored": result.scored, "events": result.events,
            "seconds": result.seconds, "seconds_by_stage": result.stages,
            **{key: clean(result.mean(key)) for key in PER_WINDOW}}
