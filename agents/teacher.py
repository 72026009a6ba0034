"""Precomputed teacher targets: per-window contrast-maximisation flows of a whole dataset,
solved once on the recordings' full sensor frames and stored, so that a teacher run
(``TrainConfig.loss="teacher"``) regresses onto them instead of solving every unroll again.

Why: solving the teacher inside every update costs most of the update (on the project's
2-core CPU about 3x the network's forward and backward at 64x64 crops, 8 envs, 4 windows,
capped at 8,000 events per window), so a run makes ~0.6 steps/s against ~1.4 for the
supervised reference. Solved once, the teacher can also afford what is too slow per update:
all events, the full frame (no crop borders), a finer last grid (16 cells) and a step size that
grows with the window's length (a 4-frame window moves up to ~4x as far as a 1-frame one, and
Adam's steps are bounded by ``lr``).

File (h5), one group per recording, named by the recording::

    /<name>/bounds  (K, 2) int64 µs: the windows [t_start, t_end)
    /<name>/grid    (K, 2, gh, gw) float32 pixels per window: the solved coarse flow; the
                    target is its bilinear upsampling to the sensor frame (align_corners=False)
    /<name> attrs:  "sensor_size" (height, width) of that recording (recordings may differ)
    attrs: "config" (JSON: data, window sizes, solver settings, first sensor size), "complete" (bool)

A run's windows are looked up by (recording, t_start, t_end); the env's crop and flips
(``info["crop"]``, ``info["flips"]``) map the full-frame target into the env's frame. The
teacher sees only events, so a run on these targets stays unsupervised.
"""

from __future__ import annotations

import io
import json
import os
import shutil
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Sequence

import h5py
import numpy as np
import torch
import torch.nn.functional as F

from envs.atomic import remove_stale_temporaries, temporary_path
from envs.dataset import resolve_data
from envs.env import EventFlowEnv
from envs.windows import Window, window_bounds
from losses import CMAX_WEIGHTS, EventBatch, LossSpec, contrast_maximisation_flow

from .cmax import check_solver_settings
from .policy import ZeroFlowPolicy
from .rollout import rollout

__all__ = ["TeacherSettings", "TeacherTargets", "compute_teacher_targets", "count_windows", "TeacherCacheError",
           "score_targets", "derive_targets", "copy_targets", "merge_targets"]

FORMAT = "evflow-teacher-targets"


class TeacherCacheError(ValueError):
    """A teacher-target file that is missing, of another kind, incomplete or lacks a window (the
    message names the file)."""


@dataclass
class TeacherSettings:
    """The contrast-maximisation solve (``losses.contrast_maximisation_flow``) of every window."""

    grids: tuple = (4, 8, 16)  # coarse-to-fine cells along the longer side (16: finer than the per-update default)
    steps: int | tuple = 40  # Adam steps per level (one for all, or one per level)
    lr_per_frame: float = 0.05  # Adam step size in pixels, times the window's length in frames
    sensor_scales: tuple | None = None  # sensor-grid coarsening per level (None: sensor pixels throughout)
    lr_decay: float = 1.0  # the step size falls by this factor over the solve
    lambda_1: float = CMAX_WEIGHTS.lambda_1
    lambda_2: float = CMAX_WEIGHTS.lambda_2
    alpha: float = CMAX_WEIGHTS.alpha
    border_penalty: float = CMAX_WEIGHTS.border_penalty
    border_ramp: float = CMAX_WEIGHTS.border_ramp
    flow_scaling: float = 32.0  # the loss's smoothness normalisation (the training runs' value)
    evidence_prior: float = 0.0  # a prior toward zero flow of weight evidence_prior / the window's events (agents.cmax.CMaxSettings)

    def __post_init__(self) -> None:
        check_solver_settings(self, "TeacherSettings")

    @property
    def loss_spec(self) -> LossSpec:
        """The loss of the solve (losses.LossSpec, from the fields that bear its settings' names)."""
        return LossSpec.from_options(self)

    @property
    def weights(self) -> LossSpec:
        """:attr:`loss_spec` under its earlier name."""
        return self.loss_spec

    def describe(self) -> dict:
        """The settings as a target file's config records them (no evidence prior: not named, as
        in the files made before it existed)."""
        out = asdict(self)
        if not out["evidence_prior"]:
            del out["evidence_prior"]
        return out


def _windows_of(env: EventFlowEnv, sequence: int) -> list[Window]:
    """Every window of one recording at the env's window size (no crop, no flips)."""
    return [step.window for step in rollout(ZeroFlowPolicy(), env, options={"sequence": sequence})]


def count_windows(data, window_sizes: Sequence[int], max_windows: int | None = None) -> int:
    """How many ``frames`` windows ``compute_teacher_targets`` solves for ``data``."""
    sources = resolve_data(data)
    try:
        return sum(len(window_bounds(source.reader(), "frames", int(k))[:max_windows])
                   for source in sources for k in set(window_sizes))
    finally:
        for source in sources:
            source.close()


def compute_teacher_targets(
    data,
    out: str | os.PathLike,
    *,
    window_sizes: Sequence[int] = (1, 2, 3, 4),
    settings: TeacherSettings | None = None,
    batch_size: int = 16,
    device: str = "cpu",
    progress=None,
    max_windows: int | None = None,
) -> Path:
    """Solve every ``frames`` window of ``data`` (each size in ``window_sizes``) and write ``out``
    (``max_windows``: only the first that many of each recording and size, e.g. to score a
    solver on part of a large split; a training run needs them all).

    Resumable: each finished recording is written at once (atomically) into the folder
    ``out + ".parts"``; a rerun with the same data and settings skips those already there (a kill
    at any moment loses at most the recording being solved); ``out`` appears, written whole then
    renamed, only when every recording is done. ``progress``: optional callable(done_windows,
    recording_name), e.g. a tqdm bar's update. Returns ``out``.
    """
    settings = settings or TeacherSettings()
    out = Path(out)
    sizes = sorted({int(k) for k in window_sizes})
    if not sizes or sizes[0] < 1:
        raise ValueError(f"window_sizes must be positive frame counts, got {list(window_sizes)}")
    names = [source.name for source in resolve_data(data)]
    first_env = EventFlowEnv(data, window="frames", compute_reward=False, sequences=[0])
    config = {"format": FORMAT, "data": data if isinstance(data, str) else [str(d) for d in np.atleast_1d(data)],
              "window_sizes": sizes, "sensor_size": list(first_env.sensor_size), **settings.describe()}
    if max_windows is not None:
        config["max_windows"] = int(max_windows)
    first_env.close()
    config = json.loads(json.dumps(config))  # tuples as lists, as they read back
    parts = out.with_name(out.name + ".parts")
    parts.mkdir(parents=True, exist_ok=True)
    config_path = parts / "config.json"
    if config_path.exists() and json.loads(config_path.read_text()) != config:
        raise TeacherCacheError(f"{parts}: an unfinished run with other settings is there; delete it or pass "
                                f"the same settings ({json.loads(config_path.read_text())})")
    _replace_with(config_path, lambda tmp: tmp.write_text(json.dumps(config)))
    for index, name in enumerate(names):
        part = parts / f"{index:05d}.npz"
        if part.exists():  # done by an earlier, interrupted run
            if progress is not None:
                with np.load(part) as done:
                    progress(len(done["bounds"]), name)
            continue
        arrays = _solve_recording(data, index, name, sizes, settings, batch_size=batch_size, device=device,
                                  progress=progress, max_windows=max_windows)
        _replace_with(part, lambda tmp, arrays=arrays: tmp.write_bytes(_npz_bytes(arrays)))

    _replace_with(out, lambda tmp: _assemble(tmp, config, parts, len(names)))
    shutil.rmtree(parts)
    return out


def _assemble(path: Path, config: dict, parts: Path, count: int) -> None:
    """Write the target file (module docstring) at ``path`` from the ``count`` part files in ``parts``."""
    with h5py.File(path, "w") as f:
        f.attrs["config"] = json.dumps(config)
        for index in range(count):
            with np.load(parts / f"{index:05d}.npz") as part:
                group = f.create_group(str(part["name"]))
                group.attrs["sensor_size"] = tuple(int(v) for v in part["sensor_size"])
                group["bounds"] = part["bounds"]
                group["grid"] = part["grid"]
        f.attrs["complete"] = True


def _solve_recording(data, index: int, name: str, sizes: list[int], settings: TeacherSettings, *, batch_size: int,
                     device: str, progress, max_windows: int | None) -> dict[str, np.ndarray]:
    """The solved targets of recording ``index`` of ``data`` at every window length of ``sizes``
    (frames), as the arrays of its part file: name, sensor_size, bounds (K, 2), grid (K, 2, gh, gw)."""
    # one env per recording and window length: each recording in its own frame
    envs = {k: EventFlowEnv(data, window="frames", window_size=k, compute_reward=False, sequences=[index])
            for k in sizes}
    H, W = envs[sizes[0]].sensor_size
    bounds, grids = [], []
    for k in sizes:  # one solve per window length: each has its own step size
        windows = _windows_of(envs[k], 0)[:max_windows]
        for start in range(0, len(windows), batch_size):
            chunk = windows[start : start + batch_size]
            batch = EventBatch.from_windows(chunk, device=device)
            counts = [len(w.events) for w in chunk]
            grids.extend(_solve_coarse(batch, H, W, settings, lr=settings.lr_per_frame * k, counts=counts))
            if progress is not None:
                progress(len(chunk), name)
        bounds += [[w.t_start, w.t_end] for w in windows]
    for env in envs.values():
        env.close()
    return {"name": np.array(name), "sensor_size": np.array((H, W), np.int64),
            "bounds": np.array(bounds, np.int64).reshape(-1, 2),
            "grid": torch.stack(grids).numpy().astype(np.float32)}


def copy_targets(source: str | os.PathLike, out: str | os.PathLike, dtype=None) -> Path:
    """Copy a complete target file to ``out``, compressed (gzip, byte shuffle): the copy a
    repository can keep so that a new machine need not solve them again. dtype: the flow grids'
    stored type (e.g. ``np.float16``: half the size, at most ~0.016 px off at 32 px; read back as
    float32); None keeps them exactly."""
    TeacherTargets(source)  # refuses an incomplete or foreign file, naming it
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)

    def write(tmp: Path) -> None:
        with h5py.File(source, "r") as src, h5py.File(tmp, "w") as dst:
            for key, value in src.attrs.items():
                dst.attrs[key] = value
            for name, group in src.items():
                copy = dst.create_group(name)
                for key, value in group.attrs.items():
                    copy.attrs[key] = value
                for key, data in group.items():
                    values = data[()]
                    if dtype is not None and key == "grid":
                        values = values.astype(dtype)
                    copy.create_dataset(key, data=values, compression="gzip", compression_opts=9, shuffle=True)

    _replace_with(out, write)
    return out


def _take_windows(path, f: h5py.File, sizes: Sequence[int], smallest: int, grids: dict[str, list],
                  bounds: dict[str, list], sizes_of: dict[str, tuple]) -> None:
    """Add to ``bounds`` and ``grids`` (per recording) the windows of the open part ``f`` (read
    from ``path``) whose length is one of ``sizes`` frames (``smallest``: the part's smallest
    window size), and each recording's sensor size to ``sizes_of``; a recording at another
    sensor size or grid shape than in the parts before raises ValueError."""
    for name, group in f.items():
        b, g = group["bounds"][()], group["grid"][()].astype(np.float32)
        frame = (b[:, 1] - b[:, 0]).min() / smallest
        length = np.rint((b[:, 1] - b[:, 0]) / frame).astype(int)
        keep = np.isin(length, list(sizes))
        if name in sizes_of and tuple(sizes_of[name]) != tuple(group.attrs["sensor_size"]):
            raise ValueError(f"{path}: recording {name} at another sensor size than in the other parts")
        if grids.get(name) and grids[name][0].shape[1:] != g.shape[1:]:
            raise ValueError(f"{path}: recording {name} with {g.shape[2:]} grids, the other parts "
                             f"{grids[name][0].shape[2:]}")
        sizes_of[name] = tuple(int(v) for v in group.attrs["sensor_size"])
        bounds.setdefault(name, []).append(b[keep])
        grids.setdefault(name, []).append(g[keep])


def merge_targets(parts: Sequence[tuple[str | os.PathLike, Sequence[int]]], out: str | os.PathLike,
                  dtype=None) -> Path:
    """One target file from several complete ones: from each ``(path, sizes)`` the windows whose
    length is one of ``sizes`` frames (a window's length in frames is its duration over the
    frame interval, the shortest window of that recording and file divided by the file's
    smallest window size). E.g. 1-frame targets of one solver with 2- and 4-frame targets of a
    stronger one. Parts of the same data must share their recordings' grid and sensor sizes;
    parts of other data (e.g. two training splits) must hold other recordings, and the file's
    data is then the list of theirs. A window given by two parts raises ValueError. dtype as
    :func:`copy_targets` (stored grids; None: as read)."""
    grids: dict[str, list] = {}
    bounds: dict[str, list] = {}
    sizes_of: dict[str, tuple] = {}
    configs = []
    data_recordings: dict[str, set] = {}  # each part's recordings
    for path, sizes in parts:
        config = TeacherTargets(path).config  # refuses an incomplete or foreign file, naming it
        configs.append({"source": Path(path).name, "window_sizes": sorted(int(k) for k in sizes), "config": config})
        with h5py.File(path, "r") as f:
            other_data = [c for c in configs[:-1] if c["config"]["data"] != config["data"]]
            shared = sorted(set(f) & {name for c in other_data for name in data_recordings[c["source"]]})
            if shared:
                raise ValueError(f"{path}: targets of data {config['data']!r} for recording {shared[0]} that a part "
                                 f"of other data ({other_data[0]['config']['data']!r}) holds too")
            data_recordings[configs[-1]["source"]] = set(f)
            _take_windows(path, f, sizes, min(config["window_sizes"]), grids, bounds, sizes_of)
    first = configs[0]["config"]
    datas = []  # the parts' data, in order, each once
    for c in configs:
        for item in np.atleast_1d(c["config"]["data"]).tolist():
            if item not in datas:
                datas.append(item)
    # no solver settings at the top: each part keeps its own in merged_from (parts may be solved differently)
    merged = {"format": FORMAT, "data": datas[0] if len(datas) == 1 else datas, "sensor_size": first["sensor_size"],
              "window_sizes": sorted({int(k) for _, sizes in parts for k in sizes}), "merged_from": configs}

    def write(tmp: Path) -> None:
        with h5py.File(tmp, "w") as f:
            f.attrs["config"] = json.dumps(merged)
            for name in bounds:
                b, g = np.concatenate(bounds[name]), np.concatenate(grids[name])
                if len({tuple(row) for row in b.tolist()}) != len(b):
                    raise ValueError(f"recording {name}: a window is given by more than one part")
                group = f.create_group(name)
                group.attrs["sensor_size"] = sizes_of[name]
                group.create_dataset("bounds", data=b, compression="gzip", compression_opts=9, shuffle=True)
                group.create_dataset("grid", data=g if dtype is None else g.astype(dtype), compression="gzip",
                                     compression_opts=9, shuffle=True)
            f.attrs["complete"] = True

    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    _replace_with(out, write)
    return out


def _npz_bytes(arrays: dict) -> bytes:
    buffer = io.BytesIO()
    np.savez(buffer, **arrays)
    return buffer.getvalue()


def _replace_with(path: Path, write) -> None:
    """``write(tmp)`` a sibling temporary file (envs.atomic), then rename it to ``path`` (never
    half-written); a killed writer's leftover temporary is removed first."""
    remove_stale_temporaries(path)
    tmp = temporary_path(path)
    try:
        write(tmp)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def _solve_coarse(batch: EventBatch, height: int, width: int, s: TeacherSettings, *, lr: float,
                  counts: Sequence[int]) -> torch.Tensor:
    """(B, 2, gh, gw) the last level's coarse flow (its upsampling is the target); counts: each
    window's events (the evidence prior's weight)."""
    prior = [s.evidence_prior / max(int(n), 1) for n in counts] if s.evidence_prior else 0.0
    flow = contrast_maximisation_flow(
        batch, height, width, grids=s.grids, steps=s.steps if isinstance(s.steps, int) else tuple(s.steps), lr=lr,
        flow_scaling=s.flow_scaling, weights=s.loss_spec, return_coarse=True,
        sensor_scales=s.sensor_scales, lr_decay=s.lr_decay, prior_weight=prior,
    )
    return flow.cpu()


class TeacherTargets:
    """Look-up of precomputed targets (see the module docstring), in the env's frame."""

    def __init__(self, path: str | os.PathLike) -> None:
        self.path = Path(path)
        if not self.path.is_file():
            raise TeacherCacheError(f"teacher targets {self.path}: no such file (make it with scripts/teacher_targets.py)")
        try:
            f = h5py.File(self.path, "r")
        except OSError as err:
            raise TeacherCacheError(f"teacher targets {self.path}: not an h5 file ({err})") from None
        with f:
            config = json.loads(f.attrs.get("config", "{}"))
            if config.get("format") != FORMAT:
                raise TeacherCacheError(f"teacher targets {self.path}: not a teacher-target file (no '{FORMAT}' config)")
            if not bool(f.attrs.get("complete", False)):
                raise TeacherCacheError(f"teacher targets {self.path}: incomplete (its run did not finish)")
            self.config = config
            self.sensor_size = tuple(config["sensor_size"])
            self._index: dict[tuple[str, int, int], torch.Tensor] = {}
            self._sizes: dict[str, tuple[int, int]] = {}
            for name, group in f.items():
                size = group.attrs.get("sensor_size", self.sensor_size)
                self._sizes[name] = (int(size[0]), int(size[1]))
                grid = torch.from_numpy(group["grid"][()]).float()
                for (t0, t1), g in zip(group["bounds"][()].tolist(), grid):
                    self._index[(name, int(t0), int(t1))] = g

    def __len__(self) -> int:
        return len(self._index)

    def holds(self, sequence: str, t_start: int, t_end: int) -> bool:
        """Whether the file has a target for the window ``[t_start, t_end)`` of ``sequence``."""
        return (str(sequence), int(t_start), int(t_end)) in self._index

    def grid(self, sequence: str, t_start: int, t_end: int) -> torch.Tensor:
        """(2, gh, gw) the stored coarse grid of one window (pixels per window, sensor frame)."""
        key = (str(sequence), int(t_start), int(t_end))
        if key not in self._index:
            raise TeacherCacheError(
                f"teacher targets {self.path}: no window [{t_start}, {t_end}) of recording {sequence!r} (the file "
                f"holds data {self.config['data']!r} at window sizes {self.config['window_sizes']} frames); "
                "make targets for the run's data and window sizes")
        return self._index[key]

    def sensor_size_of(self, sequence: str) -> tuple[int, int]:
        """(H, W) of one recording (the file's sensor size where it names none)."""
        return self._sizes.get(str(sequence), self.sensor_size)

    def target(self, sequence: str, t_start: int, t_end: int, crop=None, flips=(False, False, False)) -> torch.Tensor:
        """(2, h, w) float32 pixels per window: the target of one window in the env's frame.

        crop: ``(top, left, h, w)`` in the sensor frame (default: the whole frame); flips:
        ``(h, v, p)`` as the env applied them (a polarity flip leaves the flow unchanged)."""
        grid = self.grid(sequence, t_start, t_end)
        H, W = self.sensor_size_of(sequence)
        top, left, h, w = (0, 0, H, W) if crop is None else (int(v) for v in crop)
        flow = F.interpolate(grid[None], size=(H, W), mode="bilinear", align_corners=False)[0]
        flow = flow[:, top : top + h, left : left + w]
        if flips[0]:  # the env mirrors x -> w - 1 - x: the field mirrors and its x component flips sign
            flow = flow.flip(-1) * torch.tensor([-1.0, 1.0]).view(2, 1, 1)
        if flips[1]:
            flow = flow.flip(-2) * torch.tensor([1.0, -1.0]).view(2, 1, 1)
        return flow.contiguous()

    def targets_from_info(self, info: dict, num_envs: int) -> torch.Tensor:
        """(num_envs, 2, h, w): the targets of a vector env's current windows (its stacked info)."""
        return torch.stack([
            self.target(info["sequence"][i], info["window"][i].t_start, info["window"][i].t_end, info["crop"][i],
                        info["flips"][i])
            for i in range(num_envs)
        ])


def _smoothed(velocity: torch.Tensor, smooth: int) -> torch.Tensor:
    """Each of the (K, 2, H, W) velocities averaged with its ``smooth`` neighbours on each side
    (a triangular weight, 1 at the window, falling to 0 after smooth + 1; the ends repeated)."""
    weights = torch.tensor([smooth + 1 - abs(d) for d in range(-smooth, smooth + 1)], dtype=torch.float32)
    padded = torch.cat([velocity[:1].expand(smooth, *velocity.shape[1:]), velocity,
                        velocity[-1:].expand(smooth, *velocity.shape[1:])])
    return sum(w * padded[i : i + len(velocity)] for i, w in enumerate(weights)) / weights.sum()


def _derived_windows(reader, sizes: list[int], long: np.ndarray, velocity: torch.Tensor,
                     partial: bool) -> tuple[list[list[int]], list[torch.Tensor]]:
    """The bounds and flows of every ``sizes``-frame window of ``reader``: the velocity of the
    ``long`` windows it overlaps, weighted by the overlap (past the last: the nearest one's),
    times its duration; ``partial``: only windows within the long ones solved."""
    bounds, out_grids = [], []
    for k in sizes:
        for t0, t1 in window_bounds(reader, "frames", k)[:, :2].tolist():
            if partial and t1 > long[-1, 1]:
                break  # past the solved span
            overlap = np.clip(np.minimum(long[:, 1], t1) - np.maximum(long[:, 0], t0), 0, None)
            if overlap.sum() == 0:  # past the last long window (the frames do not divide): the nearest
                overlap = (np.arange(len(long)) == np.argmin(np.abs(long.mean(1) - (t0 + t1) / 2))) * 1.0
            w = torch.from_numpy((overlap / overlap.sum()).astype(np.float32)).view(-1, 1, 1, 1)
            out_grids.append((w * velocity).sum(0) * (t1 - t0))
            bounds.append([t0, t1])
    return bounds, out_grids


def derive_targets(source: str | os.PathLike, out: str | os.PathLike, *, from_size: int,
                   window_sizes: Sequence[int] = (1, 2, 3, 4), smooth: int = 0) -> Path:
    """Targets of every ``window_sizes`` window derived from the ``from_size``-frame ones of
    ``source`` (another target file) instead of solved: a k-frame window's flow is the velocity
    of the long windows it overlaps (their flow over their duration, weighted by the overlap)
    times its own duration (the nearest long window's velocity for the few short windows after the
    last long one). Long windows are where the loss prefers the truth most often (their
    events travel further); short ones inherit that, at the price of assuming constant velocity
    within a long window.

    smooth: also average each long window's velocity with its ``smooth`` neighbours on each side
    (a triangular weight, 1 at the window, falling to 0 after smooth + 1), a prior that motion
    changes slowly. Writes ``out`` (same format, ``config`` noting the derivation); returns it.
    """
    src = TeacherTargets(source)
    if from_size not in src.config["window_sizes"]:
        raise TeacherCacheError(f"teacher targets {src.path}: no {from_size}-frame windows to derive from "
                                f"(it holds {src.config['window_sizes']})")
    if smooth < 0:
        raise ValueError(f"smooth must be >= 0 windows, got {smooth}")
    sizes = sorted({int(k) for k in window_sizes})
    config = {**src.config, "window_sizes": sizes, "derived": {"from": str(src.path.name), "from_size": from_size,
                                                                 "smooth": smooth}}
    sources = resolve_data(config["data"])

    def write(tmp: Path) -> None:
        with h5py.File(tmp, "w") as f:
            f.attrs["config"] = json.dumps(config)
            for data_source in sources:
                name, reader = data_source.name, data_source.reader()
                long = window_bounds(reader, "frames", from_size)[:, :2]
                partial = "max_windows" in src.config  # only the first long windows were solved
                long = long[[src.holds(name, a, b) for a, b in long]] if partial else long
                if len(long) == 0:
                    raise TeacherCacheError(f"teacher targets {src.path}: recording {name!r} has no {from_size}-frame "
                                            "window to derive from (shorter than one, or none solved)")
                grids = torch.stack([src.grid(name, a, b) for a, b in long])
                velocity = grids / torch.from_numpy((long[:, 1] - long[:, 0]).astype(np.float32)).view(-1, 1, 1, 1)
                if smooth:
                    velocity = _smoothed(velocity, smooth)
                bounds, out_grids = _derived_windows(reader, sizes, long, velocity, partial)
                group = f.create_group(name)
                group.attrs["sensor_size"] = src.sensor_size_of(name)
                group["bounds"] = np.array(bounds, np.int64).reshape(-1, 2)
                group["grid"] = torch.stack(out_grids).numpy().astype(np.float32)
            f.attrs["complete"] = True

    out = Path(out)
    try:
        _replace_with(out, write)
    finally:
        for data_source in sources:
            data_source.close()
    return out


def score_targets(path: str | os.PathLike, data=None, *, max_windows: int | None = None,
                  window_sizes: Sequence[int] | None = None) -> dict[str, dict[str, float]]:
    """How good stored targets are: per window length (frames), the mean over windows of the
    targets' AEE against the ground truth and of zero flow's, on pixels with events and valid
    ground truth (the evaluation's metric). ``data`` defaults to the file's own; ``max_windows``:
    the first that many windows of each recording and length; ``window_sizes``: these lengths
    (default: the file's). Returns
    ``{"1": {"aee": .., "aee_zero": .., "windows": ..}, ...}`` (keys: window lengths)."""
    from envs.representations import event_mask
    from losses import flow_error

    targets = TeacherTargets(path)
    data = targets.config["data"] if data is None else data
    sizes = targets.config["window_sizes"] if window_sizes is None else list(window_sizes)
    sums: dict[str, list[float]] = {}
    for index, source in enumerate(resolve_data(data)):
        for k in sizes:
            env = EventFlowEnv(data, window="frames", window_size=k, compute_reward=False, sequences=[index])
            for window in _windows_of(env, 0)[:max_windows]:
                if window.flow_gt is None or not len(window.events):
                    continue
                mask = event_mask(window.events, env.sensor_size)
                target = targets.target(source.name, window.t_start, window.t_end).numpy()
                err = flow_error(target, window.flow_gt, window.flow_gt_valid, mask)
                zero = flow_error(np.zeros_like(target), window.flow_gt, window.flow_gt_valid, mask)
                if err["n_pixels"]:
                    acc = sums.setdefault(str(k), [0.0, 0.0, 0])
                    acc[0] += err["aee"]
                    acc[1] += zero["aee"]
                    acc[2] += 1
            env.close()
    return {k: {"aee": a / n, "aee_zero": z / n, "ratio": a / z, "windows": n} for k, (a, z, n) in sums.items()}
