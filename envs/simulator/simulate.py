"""Run a scene through the event camera: :func:`simulate` -> :class:`SimulatedSequence`.

Sub-steps are adaptive: each step is as long as possible (up to ``max_step_us``) while no
visible scene point moves more than ``max_step_px`` (0.25 px by default) within it, so the
linear-in-time interpolation of the log intensity between renders is accurate to a fraction
of a pixel at any speed. Frames are rendered exactly at the frame times, independently of the
sub-step grid.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from envs.events import Events
from envs.readers.base import ArrayReader, FlowGT
from envs.readers.h5 import H5Writer
from envs.simulator.emulator import EventEmulator
from envs.simulator.scene import Scene, SceneConfig

__all__ = ["simulate", "SimulatedSequence", "SIMULATOR_VERSION", "log_to_uint8"]

# Bump whenever a change alters the output for a given config (invalidates on-disk caches).
SIMULATOR_VERSION = 2


# Log intensity shown as white in frames: textures span about [-3.5, 0.8] (leaves, object
# brightness offsets and shading), so nothing saturates.
LOG_WHITE = 0.8
FRAME_GAMMA = 2.2


def log_to_uint8(log_intensity: np.ndarray) -> np.ndarray:
    """Log intensity -> 8-bit frame, gamma-encoded like an ordinary 8-bit image:
    round(255 * (exp(L - LOG_WHITE)) ** (1 / 2.2)), clipped to [0, 255]."""
    return np.clip(np.rint(255.0 * np.exp((log_intensity - LOG_WHITE) / FRAME_GAMMA)), 0, 255).astype(np.uint8)


@dataclass
class SimulatedSequence:
    """One simulated recording.

    events: the whole stream (t in [0, duration_us) us, non-decreasing).
    frames: (F, H, W) uint8 intensity frames at frame_times (F,) int64 us, from 0 to
        duration_us inclusive.
    num_substeps: renders the emulator used (diagnostics).
    """

    config: SceneConfig
    events: Events
    frames: np.ndarray
    frame_times: np.ndarray
    duration_us: int
    num_substeps: int
    scene: Scene = field(repr=False)

    @property
    def sensor_size(self) -> tuple[int, int]:
        return self.config.sensor_size

    def flow_between(self, t0_us: int, t1_us: int) -> FlowGT:
        """Exact ground-truth flow over [t0_us, t1_us) (any window, any length, t1 > t0 or not):
        flow (2, H, W) float32 pixels, the displacement by t1 of the scene point visible at
        each pixel at t0; valid (H, W) bool, all True (exact everywhere, occluded points included)."""
        flow = self.scene.flow(t0_us * 1e-6, t1_us * 1e-6)
        return flow, np.ones(self.sensor_size, bool)

    def visible_layers(self, t_us: int) -> np.ndarray:
        """(H, W) int8 index of the layer seen at each pixel at t_us (0 background, k object k-1)."""
        return self.scene.visible_layers(t_us * 1e-6)

    def render(self, t_us: int) -> np.ndarray:
        """(H, W) float32 log intensity at t_us (the emulator's input)."""
        return self.scene.render(t_us * 1e-6)

    def reader(self, name: str = "synthetic") -> ArrayReader:
        """An in-memory :class:`~envs.readers.base.ArrayReader` with exact flow for any window,
        the frame times as ground-truth grid, and the frames."""
        return ArrayReader(
            self.events,
            name=name,
            t_range=(0, self.duration_us),
            flow_fn=self.flow_between,
            flow_times=self.frame_times,
            frames=self.frames,
            frame_times=self.frame_times,
        )

    def to_h5(self, path: str | Path, *, name: str = "synthetic", provenance: dict | None = None) -> Path:
        """Write a project h5 file (envs.readers.h5): the events, the frames, and the exact flow
        between consecutive frames (the ground-truth grid). ``provenance`` is added to the
        scene config and simulator version."""
        info = {"simulator_version": SIMULATOR_VERSION, "scene_config": self.config.to_dict()}
        info.update(provenance or {})
        with H5Writer(path, self.sensor_size, name=name, provenance=info, t_start_us=0, t_end_us=self.duration_us) as writer:
            chunk = 1 << 20
            for i in range(0, len(self.events), chunk):
                writer.append_events(self.events[i : i + chunk])
            for k in range(len(self.frame_times) - 1):
                writer.add_flow(int(self.frame_times[k]), int(self.frame_times[k + 1]), *self.flow_between(int(self.frame_times[k]), int(self.frame_times[k + 1])))
            for t_us, image in zip(self.frame_times, self.frames):
                writer.add_frame(int(t_us), image)
        return Path(path)


def frame_times_us(duration_us: int, fps: float) -> np.ndarray:
    """(F,) int64: round(k * 1e6 / fps) for every k with a time <= duration_us."""
    count = int(np.floor(duration_us * fps / 1e6 + 1e-9)) + 1
    times = np.rint(np.arange(count) * (1e6 / fps)).astype(np.int64)
    return times[times <= duration_us]


def simulate(
    config: SceneConfig,
    duration_s: float = 1.0,
    *,
    fps: float = 30.0,
    max_step_px: float = 0.25,
    max_step_us: int = 2000,
    progress: Callable[[float], None] | None = None,
) -> SimulatedSequence:
    """Simulate ``duration_s`` seconds of ``config``.

    fps: frame rate of the intensity frames (and so of the ground-truth grid).
    max_step_px: largest motion of any visible point within one sub-step (px).
    max_step_us: longest sub-step (us), for slow scenes.
    progress: optional callback, called with the fraction done (0..1) every ~50 sub-steps.
    Deterministic: the same config and arguments give identical events and frames.
    """
    duration_us = int(round(duration_s * 1e6))
    if duration_us <= 0:
        raise ValueError(f"duration_s must be positive, got {duration_s}")
    scene = Scene(config)
    emulator_rng = np.random.default_rng([config.seed, 2])
    previous = scene.render(0.0)
    emulator = EventEmulator(previous, config.sensor, emulator_rng)

    parts: list[tuple[np.ndarray, ...]] = []
    t = 0
    dt = max_step_us
    steps = 0
    while t < duration_us:
        # longest step within bounds; shrink until the motion bound holds (grow back slowly)
        dt = min(max_step_us, int(dt * 1.5) + 1, duration_us - t)
        while dt > 1:
            moved = scene.max_displacement(t * 1e-6, (t + dt) * 1e-6)
            if moved <= max_step_px:
                break
            dt = max(1, int(dt * 0.95 * max_step_px / moved))
        current = scene.render((t + dt) * 1e-6)
        part = emulator.step(previous, current, t, t + dt)
        if len(part[0]):
            parts.append(part)
        previous = current
        t += dt
        steps += 1
        if progress is not None and steps % 50 == 0:
            progress(t / duration_us)
    if progress is not None:
        progress(1.0)

    h, w = config.sensor_size
    if parts:
        x, y, ts, p = (np.concatenate([part[i] for part in parts]) for i in range(4))
        events = Events(x, y, ts, p, (h, w))
    else:
        events = Events.empty((h, w))
    times = frame_times_us(duration_us, fps)
    frames = np.stack([log_to_uint8(scene.render(tf * 1e-6)) for tf in times])
    return SimulatedSequence(config, events, frames, times, duration_us, steps, scene)
