"""Benchmark protocols: MVSEC and DSEC scored the way published numbers are (docs/protocols.md).

A protocol hands :func:`agents.evaluation.evaluate` three things per recording: the reader
options (``data_options``), the windows to evaluate (``windows(reader)``) and a scorer
(``scorer(reader)``, returning ``score(flow, info, window, size, dt_ratio) -> (metrics, mask)``).

- :class:`MVSECProtocol`: the valid ranges index the 20 Hz ground-truth timestamps; windows of
  dt image frames (or 20 Hz ground-truth steps) inside that span, contiguous or overlapping;
  Zhu-compatible ground truth by default; AEE and outlier % over pixels with events and valid
  ground truth, the car's hood left out of the outdoor sequences, hot pixels optionally left out
  of the event mask.
- :class:`DSECProtocol`: every pixel with valid ground truth scored (no event mask) with EPE,
  1PE, 2PE, 3PE and angular error; windows are the ground-truth intervals, or the test-set
  timestamps. :class:`DSECSubmissionWriter` writes predictions in the benchmark's layout.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Literal

import numpy as np

from envs.readers.dsec import encode_flow_png, read_test_timestamps
from envs.readers.mvsec import MVSEC_CROP, MVSEC_GT_MODES, mvsec_eval_windows, mvsec_hood_row
from envs.representations import event_mask
from envs.windows import Window
from losses.metrics import dense_flow_error, flow_error

__all__ = ["DSECProtocol", "DSECSubmissionWriter", "DSEC_METRICS", "HotPixelFilter", "MVSECProtocol", "dsec_table"]

#: the DSEC benchmark's columns (our key: "aee" is the EPE, so the common tables show it)
DSEC_METRICS = {"aee": "EPE", "1pe": "1PE %", "2pe": "2PE %", "3pe": "3PE %", "ae": "AE deg"}

Score = Callable[[np.ndarray, dict, dict, tuple, float], tuple[dict, np.ndarray]]


def _check_choice(name: str, value, allowed) -> None:
    if value not in allowed:
        raise ValueError(f"{name} must be one of {tuple(allowed)}, got {value!r}")


def _window_mask(window: Window, size: tuple[int, int]) -> np.ndarray:
    return event_mask(window.events, size)


class HotPixelFilter:
    """Hot pixels of one recording, found online from the windows seen so far.

    Event counts per pixel are summed over the windows; after ``min_windows`` windows a pixel is
    hot when its total exceeds the mean plus ``sigma`` standard deviations of the totals of the
    pixels that fired at all (a stuck pixel fires in every window, far above moving edges).
    """

    def __init__(self, size: tuple[int, int], sigma: float = 5.0, min_windows: int = 1) -> None:
        if sigma <= 0:
            raise ValueError(f"hot-pixel sigma must be > 0, got {sigma}")
        self.size = (int(size[0]), int(size[1]))
        self.sigma, self.min_windows = float(sigma), int(min_windows)
        self.counts = np.zeros(self.size[0] * self.size[1], np.float64)
        self.windows = 0

    def __call__(self, window: Window) -> np.ndarray:
        """Add a window's events (``window.events``) and return the (H, W) bool hot-pixel mask."""
        h, w = self.size
        x = np.clip(np.floor(np.asarray(window.events.x, np.float64) + 0.5).astype(np.int64), 0, w - 1)
        y = np.clip(np.floor(np.asarray(window.events.y, np.float64) + 0.5).astype(np.int64), 0, h - 1)
        self.counts += np.bincount(y * w + x, minlength=h * w)
        self.windows += 1
        active = self.counts[self.counts > 0]
        if self.windows < self.min_windows or len(active) < 2:
            return np.zeros(self.size, bool)
        threshold = active.mean() + self.sigma * active.std()
        return (self.counts > threshold).reshape(self.size)


@dataclass
class MVSECProtocol:
    """MVSEC (Zhu et al. 2018) as the published tables score it.

    dt: window length in grid steps (1 or 4). stride: grid steps between window starts, None =
    dt (contiguous, Hagenaars); 1 with dt = 4 gives the overlapping windows of Zhu,
    Spike-FlowNet and tub-rip. grid: "images" (grayscale frame times, EV-FlowNet's dt) or "gt"
    (the 20 Hz ground-truth times, the E-RAFT / idnet evaluation). ground_truth: "zhu" (a window
    shorter than the 20 Hz interval holding its start gets that map scaled by dt / gt_dt) or
    "chain" (maps chained through time). outdoor_cut: "time" (222.4-240.4 s) or "frames"
    (ground-truth indices 4356-4706). hood: leave the car's hood out of the outdoor scores.
    hot_pixel_sigma: None, or leave pixels found hot by :class:`HotPixelFilter` out of the event
    mask.
    """

    dt: int = 1
    stride: int | None = None
    grid: Literal["images", "gt"] = "images"
    ground_truth: Literal["zhu", "chain"] = "zhu"
    outdoor_cut: Literal["time", "frames"] = "time"
    hood: bool = True
    hot_pixel_sigma: float | None = None

    def __post_init__(self) -> None:
        _check_choice("dt", self.dt, (1, 4))
        _check_choice("grid", self.grid, ("images", "gt"))
        _check_choice("ground_truth", self.ground_truth, MVSEC_GT_MODES)
        _check_choice("outdoor_cut", self.outdoor_cut, ("time", "frames"))
        if self.stride is not None and self.stride < 1:
            raise ValueError(f"stride must be >= 1 grid step, got {self.stride}")

    @property
    def data_options(self) -> dict:
        """Reader options: the central 256 x 256 crop and the ground-truth mode."""
        return {"crop": MVSEC_CROP, "gt_mode": self.ground_truth}

    def describe(self) -> str:
        stride = self.dt if self.stride is None else self.stride
        grid = "image frames" if self.grid == "images" else "20 Hz ground-truth steps"
        return (f"MVSEC dt = {self.dt} {grid}, stride {stride}, {self.ground_truth} ground truth"
                + (", hood out" if self.hood else "") + (", hot pixels out" if self.hot_pixel_sigma else ""))

    def windows(self, reader) -> np.ndarray:
        """(K, 2) µs windows of ``reader`` inside its scored span (:func:`mvsec_eval_windows`)."""
        return mvsec_eval_windows(reader, self.dt, getattr(reader, "sequence", reader.name),
                                  outdoor_cut=self.outdoor_cut, stride=self.stride, grid=self.grid)

    def scored_pixels(self, reader, size: tuple[int, int]) -> np.ndarray:
        """(H, W) bool: the pixels a window may be scored on (all but the hood rows)."""
        keep = np.ones(size, bool)
        row = mvsec_hood_row(getattr(reader, "sequence", reader.name), getattr(reader, "crop", None))
        if self.hood and row is not None:
            keep[max(row, 0):] = False
        return keep

    def scorer(self, reader) -> Score:
        """The score of one recording's windows: AEE / outlier % (``losses.flow_error``) over
        pixels with events (less hot pixels) and valid ground truth, hood rows left out."""
        hot = None
        keep_cache: dict = {}

        def score(flow, info, window, size, dt_ratio):
            size = tuple(size)
            if size not in keep_cache:
                keep_cache[size] = self.scored_pixels(reader, size)
            nonlocal hot
            mask = _window_mask(window, size) & keep_cache[size]
            if self.hot_pixel_sigma:
                if hot is None:
                    hot = HotPixelFilter(size, self.hot_pixel_sigma)
                mask &= ~hot(window)
            err = flow_error(flow, info["flow_gt"], info["flow_gt_valid"], mask, dt_ratio=dt_ratio)
            return err, mask & info["flow_gt_valid"]

        return score


@dataclass
class DSECProtocol:
    """DSEC (Gehrig et al. 2021) as its benchmark scores flow: dense, on every pixel with valid
    ground truth, events or not.

    test_timestamps: None (windows = the recording's ground-truth intervals), or the folder of
    ``<sequence>.csv`` test timestamps (or one such file) whose rows are the windows.
    """

    test_timestamps: str | os.PathLike | None = None

    def describe(self) -> str:
        what = "ground-truth intervals" if self.test_timestamps is None else "test-set timestamps"
        return f"DSEC, {what}, dense (valid ground truth, no event mask)"

    def timestamps(self, reader) -> np.ndarray:
        """(K, 3) int64 ``(from_us, to_us, file_index)`` of ``reader``'s test sequence."""
        if self.test_timestamps is None:
            raise ValueError("no test timestamps given")
        path = Path(self.test_timestamps)
        if path.is_dir():
            path = path / f"{reader.name}.csv"
        if not path.exists():
            raise FileNotFoundError(f"{path}: no test timestamps for sequence {reader.name!r}")
        return read_test_timestamps(path)

    def windows(self, reader) -> np.ndarray:
        if self.test_timestamps is not None:
            return self.timestamps(reader)[:, :2]
        intervals = reader.flow_intervals() if hasattr(reader, "flow_intervals") else None
        if intervals is None:
            raise ValueError(f"{reader.name}: no ground-truth intervals (pass flow_dir=) and no test timestamps")
        return np.asarray(intervals, np.int64).reshape(-1, 2)

    def scorer(self, reader) -> Score:
        """EPE, 1PE, 2PE, 3PE (%) and angular error over valid ground-truth pixels
        (``losses.dense_flow_error``); the prediction scaled by ``dt_ratio`` first."""

        def score(flow, info, window, size, dt_ratio):
            valid = np.asarray(info["flow_gt_valid"], bool)
            err = dense_flow_error(np.asarray(flow, np.float64) * dt_ratio, info["flow_gt"], valid)
            metrics = {"aee": err["epe"], **{k: err[k] for k in ("1pe", "2pe", "3pe", "ae")},
                       "n_pixels": err["n_pixels"]}
            return metrics, valid

        return score


class DSECSubmissionWriter:
    """Writes predictions in the benchmark's layout: ``<out>/<sequence>/<file_index:06d>.png``,
    16-bit RGB with x = R, y = G as ``flow * 128 + 2^15`` and B = 1 (``encode_flow_png``).

    Use as ``flow_sink`` of :func:`agents.evaluation.evaluate` with the protocol's test windows;
    each window's file index comes from the test timestamps. Flows outside the 16-bit range
    (|flow| >= 256 px) are clipped and counted in ``clipped``.
    """

    def __init__(self, out_dir: str | os.PathLike, protocol: DSECProtocol) -> None:
        if protocol.test_timestamps is None:
            raise ValueError("a DSEC submission needs the test timestamps (DSECProtocol(test_timestamps=...))")
        self.out_dir, self.protocol = Path(out_dir), protocol
        self._index: dict[str, dict[tuple[int, int], int]] = {}
        self.written: list[Path] = []
        self.clipped = 0

    def __call__(self, reader, window: Window, flow: np.ndarray) -> None:
        name = reader.name
        if name not in self._index:
            rows = self.protocol.timestamps(reader)
            self._index[name] = {(int(a), int(b)): int(k) for a, b, k in rows}
        key = (int(window.t_start), int(window.t_end))
        if key not in self._index[name]:
            raise ValueError(f"{name}: window {key} is not one of the test timestamps")
        flow = np.asarray(flow, np.float64)
        self.clipped += int((np.abs(flow) > 255.99).any(axis=0).sum())
        path = self.out_dir / name / f"{self._index[name][key]:06d}.png"
        path.parent.mkdir(parents=True, exist_ok=True)
        encode_flow_png(path, np.clip(flow, -256.0, 255.99), np.ones(flow.shape[1:], bool))
        self.written.append(path)


def dsec_table(named_results: dict, title: str = "") -> str:
    """Markdown table of the DSEC scores: one row per method, the metrics pooled over all
    windows of all sequences, and the number of windows scored."""
    head = ["method", *DSEC_METRICS.values(), "windows"]
    lines = ([f"**{title}**", ""] if title else []) + ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for method, rows in named_results.items():
        cells = [method]
        for key in DSEC_METRICS:
            total = sum(r.counts.get(key, 0) for r in rows)
            value = sum(r.sums.get(key, 0.0) for r in rows) / total if total else float("nan")
            cells.append("-" if not np.isfinite(value) else f"{value:.3f}")
        cells.append(str(sum(r.counts.get("aee", 0) for r in rows)))
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)
