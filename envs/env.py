"""``EventFlow-v0``: event windows in, optical-flow actions out, scored by -L_HMC."""

from __future__ import annotations

import multiprocessing
from typing import Any, Sequence

import gymnasium as gym
import numpy as np
import torch
from gymnasium import spaces

from envs.dataset import resolve_data
from envs.events import Events
from envs.readers._common import check_flow_gt, resolve_crop
from envs.representations import OBSERVATIONS, count_image
from envs.visualize import count_image_to_rgb, flow_to_rgb
from envs.windows import (
    DEFAULT_WINDOW_SIZES,
    MAX_WINDOW_EVENTS,
    WINDOW_MODES,
    Window,
    check_window_events,
    check_window_fits,
    window_bounds,
    window_grid,
)
from losses import LossSpec, window_loss

__all__ = ["EventFlowEnv", "OBSERVATION_KEYS", "Window", "NoWindowsError"]


class NoWindowsError(ValueError):
    """The chosen recording has no window of the requested kind (e.g. shorter than one window)."""


#: The observation parts: the image observations of envs.representations.OBSERVATIONS, and the events.
OBSERVATION_KEYS = (*OBSERVATIONS, "events")


class EventFlowEnv(gym.Env):
    """Event-camera optical flow as an episodic environment.

    An episode is one recording (a *sequence*) cut into consecutive event windows. Each
    observation shows one window; the action is the optical flow over that window; the
    reward scores the action on the window's own events with the unsupervised hybrid
    motion-compensation loss, so no ground truth is needed to train.

    **Observation** (``Dict`` of float32 ``Box``es, parts chosen with ``observations``): the
    images of ``envs.representations.OBSERVATIONS`` (their channels, bounds and builders there),
    and the events.

    - ``"count_image"``: (2, H, W) events per pixel, [ON, OFF] (paper eq. 2), in [0, 2^24].
    - ``"voxel_grid"``: (voxel_bins, H, W) signed, bilinear in time, in [-2^24, 2^24].
    - ``"count_time_image"``: (4, H, W) EV-FlowNet's input (Zhu et al.): the count image, then
      per polarity the latest event's time in the window, scaled so the latest is 1.
    - ``"events"``: (max_events, 4) rows ``(x, y, tau, p)`` of the window's events, zero
      padded; ``"num_events"``: (1,) how many rows are real. A window with more events
      than ``max_events`` is subsampled evenly for this part only (``info["window"]`` and the
      reward always use every event).

    **Action**: ``Box(-F, F, (2, H, W), float32)``: flow in pixels of displacement over the
    window (channel 0 = x, right; channel 1 = y, down), with ``F = flow_limit`` (default
    ``flow_scaling``, i.e. max(H, W): a displacement across the whole frame). Actions must be
    float32/float64 of shape (2, H, W) and finite; finite values outside the box are clipped.

    **Reward**: ``-L_HMC(action, events of the window just observed)`` (docs/method.md, "Losses":
    L_AT(0) + L_AT(1) + lambda_1 (L_EC(0) + L_EC(1)) + lambda_2 L_smooth), or ``-L_AT``
    (+ smoothing) with ``loss="at"``, border rule included: exactly
    ``-losses.window_loss(action, window, env.loss_spec, flow_scaling=env.flow_scaling)`` with
    ``window = info["window"]`` of the observation acted on. A Python float; higher is better; 0 is unattainable for a window with events.

    *Training's batched path equals -reward*: the learner (``agents/learner.py``) runs its envs
    with ``compute_reward=False`` and computes the same ``window_loss`` itself, with gradients,
    on B windows padded into one ``EventBatch`` (``EventBatch.from_windows(info["window"])``)
    and each window's zero-flow loss computed once (``losses.zero_flow_loss``). Padding is
    ignored, so each window's ``per_sample`` loss there is this env's -reward for the same flow
    (up to float32 rounding; tests/test_env.py checks it), when the run keeps the env's weights
    and readings (the defaults).

    *Border rule* (a deviation from the paper's loss, on by default): corners of warped events
    that leave the image are dropped by L_AT and L_EC, so a huge constant action that pushes
    every event out of the frame would score a perfect 0. The reward therefore adds
    ``border_penalty * L_HMC(zero flow) * sum_s c_s``, c_s = the mean over events of the share
    of each event's splat weight that leaves the image at reference s times
    ``min(1, d / border_ramp)``, d = how many pixels beyond the image it lands. Pushing
    everything far out then costs ``2 * border_penalty * L_HMC(zero flow)``, worse than doing
    nothing for any ``border_penalty > 0.5`` however dense the window; flows that keep events
    inside are unaffected; real motion across the border (which leaves by at most |u| pixels)
    pays only in proportion to how far it goes (without the ramp, ``border_ramp=0``, the true
    flow of 30 Hz windows on 64x64 crops scores worse than zero flow: docs/results.md).
    ``border_penalty=0`` gives the paper's loss exactly.

    **Episode end**: the end of the recording *truncates* the episode (``truncated=True``):
    the recording stopping is a limit of the data, not a terminal state of the scene, so a
    value estimate should bootstrap through it. ``terminated`` is always False. The
    observation returned with ``truncated=True`` is all zeros (there is no next window).
    ``max_episode_steps`` (through ``gymnasium.make``) cuts training chunks.

    **info**, describing the window the returned observation shows:

    - ``"window"``: the window (:class:`envs.windows.Window`): its events (``window.events``:
      numpy ``x``, ``y`` pixels, ``t`` int64 µs, ``p`` +-1, in the env's frame), its bounds
      ``window.t_start``, ``window.t_end`` (int µs, ``[t_start, t_end)``), its ground truth
      where present, and ``window.batch()``, what the loss takes. Not being a dict, a vector env
      hands it over as one object per env (windows differ in length, which Gymnasium's stacking
      of info arrays cannot hold): ``info["window"][i]``;
    - ``"sequence"`` (name), ``"sequence_index"``, ``"step"`` (window index in the episode);
    - ``"windowing"``: how this episode's windows are cut: ``"ground truth"``, ``"frames"``
      (APS frame times) or ``"time"`` (fixed 30 Hz) in ``frames`` mode, else ``"time"`` /
      ``"count"`` (``"explicit"`` with the ``windows`` reset option);
    - ``"crop"``: int64 ``(top, left, height, width)`` of the env's frame in the recording's
      sensor frame, and ``"flips"``: bool ``(h, v, p)``, the flips applied this episode (with
      them, anything computed on the whole sensor frame maps into the env's frame);
    - ``"flow_gt"`` (2, H, W) float32 pixels over the window and ``"flow_gt_valid"`` (H, W)
      bool, when the recording has ground truth for this window (checked: every valid pixel
      finite and within 4 x the sensor's longer side, else a FormatError naming the file); the
      same arrays as ``window.flow_gt`` and ``window.flow_gt_valid``, here so that a vector env
      stacks them;
    - after ``step`` only: ``"reward_components"``: dict of ``at``, ``ec``, ``smooth`` (floats,
      the scored window's loss terms; ``ec`` is reported with ``loss="at"`` too).

    Events and flows are in the env's pixel frame (after crop and flips), the frame of the
    action.

    **reset options**: ``"sequence"`` (index or name), ``"start"`` (µs: window from there),
    ``"windows"`` ((K, 2) int µs ``[t_start, t_end)`` rows: exactly these windows, e.g. an
    evaluation protocol's valid range).

    **Randomness** (all through ``self.np_random``): the sequence chosen at ``reset`` (unless
    ``options["sequence"]``), the start time when ``random_start``, the crop position when
    ``random_crop``, and the flips.

    Args:
        data: synthetic split name (default ``"synthetic-train"``), a recording path, a
            directory, or a list of these. All recordings must share one sensor size unless
            ``crop`` fixes the frame (then that crop of each, centred or placed at random);
            recordings of different sizes without ``crop`` are refused, naming the sizes (an
            env's spaces have one shape; ``agents.evaluation.evaluate`` makes one env per
            recording to score each whole).
        data_format (or ``format``): force a reader (``"evflow-h5"``, ``"mvsec"``, ``"dsec"``,
            ``"hagenaars"``, ``"ecd-text"``, ``"aedat4"``); default: detected from the file.
        data_options: keyword arguments for the reader, e.g. ``{"crop": "center256"}`` (MVSEC), or
            ``{"sensor_size": (height, width)}`` (or ``"auto"``) for Prophesee RAW / DAT and text
            files whose header gives no geometry (``envs.readers.detect``).
        sensor_size: shorthand for ``data_options["sensor_size"]``; needed for events held in
            memory (``data=`` a structured array with fields x, y, t, p in µs, tonic's layout, a
            mapping of those four arrays, or ``Events``: envs/memory.py; tonic's (width, height,
            polarities) is accepted too).
        window: ``"frames"`` (on the ground-truth grid where the recording has one, else on
            its APS frame times, else on fixed 30 Hz intervals; ``info["windowing"]`` says
            which), ``"time"`` or ``"count"``.
        window_size: grid steps (``frames``, default 1), µs (``time``, default 10 000) or
            events (``count``, default 15 000); a list of sizes draws one per episode (e.g.
            ``[1, 2, 3, 4]`` frames: training on several motion magnitudes).
        crop: None, ``(height, width)`` centred, or ``(top, left, height, width)``.
        random_crop: place the ``crop`` window at a random position in each episode (the
            whole recording stays in play while training on small crops); needs ``crop``.
        observations: which of ``OBSERVATION_KEYS`` to include.
        voxel_bins, max_events: sizes of the optional parts.
        max_window_events: the most events one window may hold (default
            ``envs.windows.MAX_WINDOW_EVENTS``, 5 000 000: about 1 GB to read, observe and score
            it); a longer window is refused with a ValueError before its events are read, so a
            file's content cannot make one window take unbounded memory. None: no bound.
        flips: False, True (all of "h", "v", "p") or a subset of ``("h", "v", "p")``:
            horizontal / vertical mirror and polarity swap, each drawn with probability
            0.5 once per episode; the ground truth is flipped to match.
        event_keep: None, a fraction ``p`` or a range ``(low, high)`` in (0, 1]: thin the events,
            keeping each with probability ``p``, drawn once per episode log-uniformly in the range
            (an augmentation: the motion, and so the ground truth, is unchanged while the events
            per pixel fall, so that a network cannot read the speed off the event density).
        loss_spec: the reward's :class:`losses.LossSpec` (the loss, its weights, the border
            rule), given whole; or, instead, some of its settings as keywords (None: the
            spec's default): loss: ``"hmc"`` or ``"at"``; lambda_1, lambda_2, alpha: the loss
            weights (paper defaults); border_penalty: the border rule's weight (default 1;
            0 = paper); border_ramp: its ramp in pixels (default 16; 0 = the plain dropped
            share). ``env.loss_spec`` holds the env's spec.
        flow_scaling: pixels per network unit in the smoothness term (default max(H, W)).
        flow_limit: F, the action bound (default flow_scaling).
        random_start: start each episode at a random window instead of the first.
        compute_reward: False skips the loss (reward 0.0), e.g. for pure evaluation rollouts.
        sequences: use only these recordings of ``data`` (indices or names), e.g. one
            training process's shard.
        env_index: this env's place in a vector env (used by
            :meth:`restore_episode_state` to pick its own entry).
        render_mode: None or ``"rgb_array"``.
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 30}

    def __init__(
        self,
        data: str | Sequence = "synthetic-train",
        *,
        data_format: str | None = None,
        format: str | None = None,
        data_options: dict | None = None,
        window: str = "frames",
        window_size: int | Sequence[int] | None = None,
        crop: Sequence[int] | None = None,
        random_crop: bool = False,
        observations: Sequence[str] = ("count_image",),
        voxel_bins: int = 5,
        max_events: int = 30_000,
        max_window_events: int | None = MAX_WINDOW_EVENTS,
        flips: bool | Sequence[str] = False,
        event_keep: float | Sequence[float] | None = None,
        loss: str | None = None,
        lambda_1: float | None = None,
        lambda_2: float | None = None,
        alpha: float | None = None,
        border_penalty: float | None = None,
        border_ramp: float | None = None,
        loss_spec: LossSpec | None = None,
        flow_scaling: float | None = None,
        flow_limit: float | None = None,
        random_start: bool = False,
        compute_reward: bool = True,
        sequences: Sequence[int | str] | None = None,
        env_index: int = 0,
        render_mode: str | None = None,
        sensor_size: Sequence[int] | str | None = None,
    ) -> None:
        if sensor_size is not None:  # events from memory, or a file without geometry
            data_options = {**(data_options or {}), "sensor_size": sensor_size}
        sizes = _window_sizes(window, window_size)
        self.window = window
        self.window_sizes = tuple(sizes)  # one is drawn per episode when there are several
        self.window_size = sizes[0]
        self.observation_keys = _observation_keys(observations)
        self.loss_spec = _loss_spec(loss_spec, loss=loss, lambda_1=lambda_1, lambda_2=lambda_2, alpha=alpha,
                                    border_penalty=border_penalty, border_ramp=border_ramp)
        self.flip_kinds = _flip_kinds(flips)
        self.event_keep = check_event_keep(event_keep)
        self.render_mode = _render_mode(render_mode, self.metadata["render_modes"])
        self.random_start = random_start
        self.compute_reward = compute_reward
        self.voxel_bins = int(voxel_bins)
        self.max_events = int(max_events)
        self.max_window_events = _max_window_events(max_window_events, window, sizes)

        self.sources = resolve_data(data, format=data_format or format, options=data_options)
        if sequences is not None:
            self.sources = _pick_sequences(self.sources, sequences)
        self.env_index = int(env_index)
        _single_thread_in_worker()
        self.sequence_names = [s.name for s in self.sources]
        self._set_frame(crop, random_crop, flow_scaling, flow_limit)
        self._clear_episode()

    def _set_frame(self, crop, random_crop: bool, flow_scaling, flow_limit) -> None:
        """The frame the env works in: the sensor size (the first recording's; without a crop
        every recording must share it), the crop and its size, the flow's scale and limit, and
        the observation and action spaces at that size."""
        first = self.sources[0].reader()
        self.sensor_size = tuple(first.sensor_size)
        self._crop_given = crop is not None
        if crop is None:
            known = {s.name: tuple(s.sensor_size) for s in self.sources if s.sensor_size is not None}
            known[self.sources[0].name] = self.sensor_size
            if len(set(known.values())) > 1:
                raise ValueError(_sizes_differ(known))
        self._crop = self._parse_crop(crop, self.sensor_size)
        self.height, self.width = self._crop[2], self._crop[3]
        if random_crop and crop is None:
            raise ValueError("random_crop=True needs crop=(height, width): the size of the randomly placed window")
        self.random_crop = bool(random_crop)
        self._origin: tuple[int, int] | None = None  # this episode's crop corner (random_crop)
        for name, value in (("flow_scaling", flow_scaling), ("flow_limit", flow_limit)):
            _check_pixels(name, value)
        self.flow_scaling = float(flow_scaling if flow_scaling is not None else max(self.height, self.width))
        self.flow_limit = float(flow_limit if flow_limit is not None else self.flow_scaling)
        self.observation_space = self._observation_space()
        self.action_space = spaces.Box(-self.flow_limit, self.flow_limit, (2, self.height, self.width), np.float32)

    def _clear_episode(self) -> None:
        """No episode yet: its windows, place, augmentations and last window and action unset."""
        self._bounds: np.ndarray | None = None
        self._windowing = ""
        self._seq_index = -1
        self._step = 0
        self._flips: dict[str, bool] = {}
        self._keep: tuple[float, int] | None = None  # this episode's (keep probability, seed) (event_keep)
        self._window: Window | None = None
        self._last_action: np.ndarray | None = None
        self._scored_window: Window | None = None

    def _observation_space(self) -> spaces.Dict:
        """The observations asked for, at the crop's size (``events``: ``max_events`` rows of
        x, y, t, p and their count)."""
        h, w = self.height, self.width
        parts: dict[str, spaces.Space] = {
            name: spaces.Box(*observation.bounds((h, w), self.voxel_bins), dtype=np.float32)
            for name, observation in OBSERVATIONS.items() if name in self.observation_keys
        }
        if "events" in self.observation_keys:
            low = np.tile(np.array([0, 0, 0, -1], np.float32), (self.max_events, 1))
            high = np.tile(np.array([w - 1, h - 1, 1, 1], np.float32), (self.max_events, 1))
            parts["events"] = spaces.Box(low, high, dtype=np.float32)
            parts["num_events"] = spaces.Box(0.0, float(self.max_events), (1,), np.float32)
        return spaces.Dict(parts)

    # ------------------------------------------------------------------------------------------
    @staticmethod
    def _parse_crop(crop, sensor_size) -> tuple[int, int, int, int]:
        if isinstance(crop, str):  # the readers' "centerN" is not an env option
            raise ValueError(f"crop must be (height, width) or (top, left, height, width), got {crop!r}")
        return resolve_crop(crop, sensor_size) or (0, 0, *sensor_size)

    def _reader(self, index: int):
        reader = self.sources[index].reader()
        if tuple(reader.sensor_size) != self.sensor_size:
            if not self._crop_given:
                raise ValueError(_sizes_differ({self.sources[0].name: self.sensor_size,
                                                self.sources[index].name: tuple(reader.sensor_size)}))
            top, left, ch, cw = self._crop
            if ch > reader.sensor_size[0] or cw > reader.sensor_size[1]:
                raise ValueError(
                    f"recording {self.sources[index].name!r} is {reader.sensor_size[0]}x{reader.sensor_size[1]} "
                    f"but the env's frame is {ch}x{cw} (set crop= to a size every recording can hold, "
                    "or use recordings of one sensor size)"
                )
        return reader

    def _crop_for(self, reader) -> tuple[int, int, int, int]:
        if self.random_crop and self._origin is not None:
            return (*self._origin, self.height, self.width)
        if tuple(reader.sensor_size) == self.sensor_size:
            return self._crop
        sh, sw = reader.sensor_size
        return ((sh - self.height) // 2, (sw - self.width) // 2, self.height, self.width)

    def _sequence_index(self, choice) -> int:
        if isinstance(choice, str):
            if choice not in self.sequence_names:
                raise ValueError(f"options['sequence']: unknown sequence {choice!r}; known: {self.sequence_names}")
            return self.sequence_names.index(choice)
        if not _is_whole(choice):
            raise ValueError(f"options['sequence'] must be a sequence name or an integer index in "
                             f"[0, {len(self.sources)}), got {choice!r}")
        index = int(choice)
        if not 0 <= index < len(self.sources):
            raise ValueError(f"options['sequence']: index {index} outside [0, {len(self.sources)})")
        return index

    # ------------------------------------------------------------------------------------------
    RESET_OPTIONS = ("sequence", "start", "windows")

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        options = dict(options or {})
        unknown = sorted(str(k) for k in options if k not in self.RESET_OPTIONS)
        if unknown:  # a misspelt key would silently do nothing
            raise ValueError(f"reset options {unknown}: unknown; EventFlowEnv.reset takes {list(self.RESET_OPTIONS)}")
        super().reset(seed=seed)
        if "sequence" in options:
            index = self._sequence_index(options["sequence"])
        else:
            index = int(self.np_random.integers(len(self.sources)))
        reader = self._reader(index)
        if "windows" in options:  # an explicit list of windows, e.g. an evaluation protocol's
            self._windowing = "explicit"
            spans = _check_windows(options["windows"])
            idx = np.array([[reader.index_at(int(a)), reader.index_at(int(b))] for a, b in spans], np.int64).reshape(-1, 2)
            bounds = np.concatenate([spans, idx], axis=1)
        else:
            if len(self.window_sizes) > 1:
                self.window_size = self.window_sizes[int(self.np_random.integers(len(self.window_sizes)))]
            try:
                check_window_fits(reader, self.window, self.window_size)
            except ValueError as err:  # a window longer than the recording: name the recording
                raise ValueError(f"recording {self.sources[index].name!r}: {err}") from None
            bounds = window_bounds(reader, self.window, self.window_size, t_from=options.get("start"))
            self._windowing = window_grid(reader)[1] if self.window == "frames" else self.window
        if len(bounds) == 0:
            raise NoWindowsError(
                f"recording {self.sources[index].name!r} has no {self.window} window of size "
                f"{self.window_size} after t={options.get('start', reader.t_start)} us"
            )
        if self.random_start and "start" not in options and len(bounds) > 1:
            bounds = bounds[int(self.np_random.integers(len(bounds))) :]
        self._bounds = bounds
        self._seq_index = index
        self._step = 0
        self._flips = {k: bool(self.np_random.random() < 0.5) for k in self.flip_kinds}
        self._keep = None
        if self.event_keep is not None:  # drawn only when asked: the stream of other runs is unchanged
            low, high = self.event_keep
            keep = float(np.exp(self.np_random.uniform(np.log(low), np.log(high)))) if high > low else low
            self._keep = (keep, int(self.np_random.integers(2**62)))
        self._origin = None
        if self.random_crop:
            sh, sw = reader.sensor_size
            self._origin = (int(self.np_random.integers(sh - self.height + 1)),
                            int(self.np_random.integers(sw - self.width + 1)))
        self._last_action = None
        self._scored_window = None
        self._window = self._load_window(0)
        return self._observation(self._window), self._info(self._window)

    def step(self, action):
        if self._window is None:
            raise RuntimeError("EventFlowEnv.step() called before reset(); call env.reset() first")
        flow = self._check_action(action)
        self._last_action = flow
        self._scored_window = self._window
        reward, components = 0.0, {}
        if self.compute_reward:
            reward, components = self._score(flow, self._window)
        self._step += 1
        truncated = self._step >= len(self._bounds)
        if truncated:
            window = self._empty_window()
            self._window = None
            observation = {k: np.zeros(s.shape, np.float32) for k, s in self.observation_space.spaces.items()}
        else:
            window = self._window = self._load_window(self._step)
            observation = self._observation(window)
        info = self._info(window)
        info["reward_components"] = components
        return observation, reward, False, truncated, info

    # ------------------------------------------------------------------------------------------
    def _check_action(self, action) -> np.ndarray:
        shape = self.action_space.shape
        if isinstance(action, torch.Tensor):
            action = action.detach().cpu().numpy()
        action = np.asarray(action)
        if action.shape != shape:
            raise ValueError(f"action must be a flow of shape {shape} (2, H, W) in pixels per window, got shape {action.shape}")
        if action.dtype not in (np.float32, np.float64):
            raise ValueError(f"action must be float32 (or float64) flow in pixels, got dtype {action.dtype}")
        if not np.isfinite(action).all():
            bad = np.argwhere(~np.isfinite(action))[0]
            raise ValueError(f"action holds a non-finite value at index {tuple(int(i) for i in bad)}: flow must be finite")
        return np.clip(action, -self.flow_limit, self.flow_limit).astype(np.float32)

    @torch.no_grad()
    def _score(self, flow: np.ndarray, window: Window) -> tuple[float, dict]:
        out = window_loss(torch.from_numpy(flow).unsqueeze(0), window, self.loss_spec, flow_scaling=self.flow_scaling)
        components = {k: float(v.reshape(-1)[0]) for k, v in out.components.items()}
        return -float(out.loss), components

    @property
    def loss_name(self) -> str:
        """The reward's loss, ``"hmc"`` or ``"at"`` (``loss_spec.loss``)."""
        return self.loss_spec.loss

    @property
    def loss_weights(self) -> LossSpec:
        """The reward's spec under its earlier name (``loss_spec``)."""
        return self.loss_spec

    @property
    def current_window(self) -> Window | None:
        """The window the last observation shows (``info["window"]``); None before ``reset``
        and after the episode's end."""
        return self._window

    def _load_window(self, k: int) -> Window:
        t_start, t_end, i_start, i_end = (int(v) for v in self._bounds[k])
        reader = self._reader(self._seq_index)
        check_window_events(i_end - i_start, self.max_window_events,
                            f"window {k} ([{t_start}, {t_end}) us) of recording {self.sequence_names[self._seq_index]!r}")
        events = reader.events_range(i_start, i_end)
        top, left, ch, cw = self._crop_for(reader)
        x, y, t, p = events.x, events.y, events.t, events.p
        cropped = (top, left, ch, cw) != (0, 0) + tuple(reader.sensor_size)
        if cropped:
            keep = (x >= left) & (x < left + cw) & (y >= top) & (y < top + ch)
            x, y, t, p = x[keep] - left, y[keep] - top, t[keep], p[keep]
            x, y = x.astype(events.x.dtype), y.astype(events.y.dtype)
        if self._flips.get("h"):
            x = (cw - 1 - x).astype(x.dtype)
        if self._flips.get("v"):
            y = (ch - 1 - y).astype(y.dtype)
        if self._flips.get("p"):
            p = (-p).astype(p.dtype)
        thinned = self._keep is not None and self._keep[0] < 1.0
        if thinned:  # the same events for window k of this episode however often it is loaded
            kept = np.random.default_rng((self._keep[1], k)).random(len(x)) < self._keep[0]
            x, y, t, p = x[kept], y[kept], t[kept], p[kept]
        if cropped or thinned or any(self._flips.values()):
            events = Events(x, y, t, p, (ch, cw))  # trusted: a crop, thinning and flips of validated events
        flow = valid = None
        gt = reader.flow_between(t_start, t_end)
        if gt is not None:
            flow, valid = gt
            check_flow_gt(flow, valid, reader.sensor_size,
                          f"{getattr(reader, 'path', reader.name)} (window [{t_start}, {t_end}) us)")
            flow = np.array(flow[:, top : top + ch, left : left + cw], np.float32)
            valid = np.array(valid[top : top + ch, left : left + cw], bool)
            if self._flips.get("h"):
                flow, valid = flow[:, :, ::-1].copy(), valid[:, ::-1].copy()
                flow[0] = -flow[0]
            if self._flips.get("v"):
                flow, valid = flow[:, ::-1].copy(), valid[::-1].copy()
                flow[1] = -flow[1]
        return Window(k, t_start, t_end, i_start, i_end, events, flow, valid)

    def _empty_window(self) -> Window:
        """What ``info`` describes after the last window: no events, at the recording's end."""
        t_end, i_end = int(self._bounds[-1][1]), int(self._bounds[-1][3])
        return Window(len(self._bounds), t_end, t_end, i_end, i_end, Events.empty((self.height, self.width)))

    def _observation(self, window: Window) -> dict[str, np.ndarray]:
        ev = window.events
        size = (self.height, self.width)
        obs: dict[str, np.ndarray] = {
            name: observation.build(ev, window.t_start, window.t_end, size, self.voxel_bins)
            for name, observation in OBSERVATIONS.items() if name in self.observation_keys
        }
        if "events" in self.observation_keys:
            n = len(ev)
            rows = np.zeros((self.max_events, 4), np.float32)
            pick = np.arange(n) if n <= self.max_events else np.linspace(0, n - 1, self.max_events).astype(np.int64)
            tau = (ev.t[pick] - window.t_start) / max(window.duration_us, 1)
            rows[: len(pick)] = np.stack([ev.x[pick], ev.y[pick], np.clip(tau, 0, 1), ev.p[pick]], axis=1)
            obs["events"] = rows
            obs["num_events"] = np.array([len(pick)], np.float32)
        return obs

    def _info(self, window: Window) -> dict[str, Any]:
        info = {
            "window": window,
            "sequence": self.sequence_names[self._seq_index],
            "sequence_index": self._seq_index,
            "step": self._step,
            "windowing": self._windowing,
            "crop": np.array(self._crop_for(self._reader(self._seq_index)), np.int64),
            "flips": np.array([self._flips.get(k, False) for k in ("h", "v", "p")], bool),
        }
        if window.flow_gt is not None:
            info["flow_gt"], info["flow_gt_valid"] = window.flow_gt, window.flow_gt_valid
        return info

    # ------------------------------------------------------------------------------------------
    def episode_state(self) -> dict[str, Any]:
        """Everything needed to continue the current episode elsewhere (checkpoints)."""
        return {
            "sequence_index": self._seq_index,
            "bounds": None if self._bounds is None else self._bounds.copy(),
            "step": self._step,
            "flips": dict(self._flips),
            "keep": self._keep,
            "origin": self._origin,
            "rng": self.np_random.bit_generator.state,
            "active": self._window is not None,
            "windowing": self._windowing,
        }

    def restore_episode_state(self, states: dict | Sequence[dict]) -> None:
        """Continue an episode saved by :meth:`episode_state`; given a list (one entry per
        env of a vector env), takes entry ``env_index``."""
        state = states if isinstance(states, dict) else states[self.env_index]
        self.np_random.bit_generator.state = state["rng"]
        self._seq_index = int(state["sequence_index"])
        self._bounds = None if state["bounds"] is None else np.asarray(state["bounds"], np.int64)
        self._step = int(state["step"])
        self._windowing = str(state.get("windowing", ""))
        self._flips = dict(state["flips"])
        keep = state.get("keep")
        self._keep = None if keep is None else (float(keep[0]), int(keep[1]))
        origin = state.get("origin")
        self._origin = None if origin is None else (int(origin[0]), int(origin[1]))
        self._last_action = self._scored_window = None
        self._window = self._load_window(self._step) if state["active"] else None

    # ------------------------------------------------------------------------------------------
    def render(self):
        if self.render_mode != "rgb_array":
            return None
        size = (self.height, self.width)
        # the window the last action was scored on; before any step, the current one
        shown = self._scored_window if self._scored_window is not None else self._window
        if shown is not None:
            counts = count_image(shown.events, size)
        else:
            counts = np.zeros((2,) + size, np.float32)
        left = count_image_to_rgb(counts)
        flow = self._last_action if self._last_action is not None else np.zeros((2,) + size, np.float32)
        right = flow_to_rgb(flow)
        return np.concatenate([left, right], axis=1)

    def __getstate__(self):
        raise TypeError("EventFlowEnv holds open recordings and cannot be pickled or copied: build another with "
                        "gymnasium.make('EventFlow-v0', ...) (a vector env takes a function that builds one)")

    def close(self) -> None:
        for source in self.sources:
            source.close()


def check_event_keep(value) -> tuple[float, float] | None:
    """``event_keep`` as ``(low, high)`` with 0 < low <= high < 1 or high = 1, or None (no thinning:
    None, 1 or (1, 1)); ValueError names a bad value."""
    if value is None:
        return None
    given = list(value) if isinstance(value, (list, tuple, np.ndarray)) else [value]
    ok = len(given) in (1, 2) and all(
        isinstance(v, (int, float, np.number)) and not isinstance(v, bool) and 0 < float(v) <= 1 for v in given)
    if not ok or float(given[0]) > float(given[-1]):
        raise ValueError(f"event_keep must be a fraction in (0, 1] or a range (low, high) of them with low <= high, "
                         f"got {value!r}")
    low, high = float(given[0]), float(given[-1])
    return None if low == 1.0 else (low, high)  # keeping every event: a plain env, its random stream unchanged


def _is_whole(value) -> bool:
    """An integer (Python or numpy), or a float with an integer value; never a bool."""
    if isinstance(value, (bool, np.bool_)):
        return False
    if isinstance(value, (int, np.integer)):
        return True
    return isinstance(value, (float, np.floating)) and np.isfinite(value) and float(value).is_integer()


def _window_sizes(window: str, window_size) -> list[int]:
    """The window sizes asked for (``window_size``: one or a list; None: the mode's default,
    ``DEFAULT_WINDOW_SIZES``) as positive ints; an unknown ``window`` mode or a size that is not
    a positive whole number is a ValueError."""
    if window not in WINDOW_MODES:
        raise ValueError(f"window must be one of {WINDOW_MODES}, got {window!r}")
    if window_size is None:
        window_size = DEFAULT_WINDOW_SIZES[window]
    given = list(window_size) if isinstance(window_size, (list, tuple, np.ndarray)) else [window_size]
    if not given or not all(_is_whole(v) and int(v) > 0 for v in given):
        raise ValueError(f"window_size must be a positive integer or a non-empty list of them "
                         f"({'grid steps' if window == 'frames' else 'us' if window == 'time' else 'events'}), "
                         f"got {window_size!r}")
    return [int(v) for v in given]


def _observation_keys(observations: Sequence[str]) -> tuple[str, ...]:
    """``observations`` as a tuple: a non-empty subset of ``OBSERVATION_KEYS``."""
    unknown = [k for k in observations if k not in OBSERVATION_KEYS]
    if unknown or not observations:
        raise ValueError(f"observations must be a non-empty subset of {OBSERVATION_KEYS}, got {list(observations)}")
    return tuple(observations)


def _render_mode(render_mode: str | None, modes: Sequence[str]) -> str | None:
    """``render_mode``: None or one of ``modes``."""
    if render_mode is not None and render_mode not in modes:
        raise ValueError(f"render_mode must be None or one of {modes}, got {render_mode!r}")
    return render_mode


def _max_window_events(max_window_events, window: str, sizes: list[int]) -> int | None:
    """``max_window_events`` as an int (or None: no bound); in ``count`` mode every window size
    must fit it."""
    if max_window_events is not None and not (_is_whole(max_window_events) and int(max_window_events) > 0):
        raise ValueError(f"max_window_events must be a positive integer or None, got {max_window_events!r}")
    limit = None if max_window_events is None else int(max_window_events)
    if window == "count":
        for size in sizes:
            check_window_events(size, limit, f"a count window of {size} events")
    return limit


def _single_thread_in_worker() -> None:
    """In a worker of an async vector env (forked by default on Linux), torch's OpenMP pool
    inherited from a parent that already ran torch ops deadlocks on first use in the child, so
    the reward runs single-threaded there (one window is small)."""
    if multiprocessing.parent_process() is not None:
        torch.set_num_threads(1)


def _flip_kinds(flips) -> tuple[str, ...]:
    """``flips`` (True: all, False: none, or a subset of "h", "v", "p") as a tuple of kinds."""
    flips = ("h", "v", "p") if flips is True else (() if flips is False else tuple(flips))
    if any(f not in ("h", "v", "p") for f in flips):
        raise ValueError(f"flips must be True/False or a subset of ('h', 'v', 'p'), got {flips}")
    return flips


def _pick_sequences(sources: list, sequences) -> list:
    """The sources ``sequences`` names (each a sequence name or an index into ``sources``), in
    that order; an unknown name, an index out of range or an empty selection is a ValueError."""
    names = [s.name for s in sources]
    picked = []
    for item in sequences:
        if isinstance(item, str):
            if item not in names:
                raise ValueError(f"sequences: unknown sequence {item!r}; known: {names}")
            item = names.index(item)
        if not 0 <= int(item) < len(sources):
            raise ValueError(f"sequences: index {item} outside [0, {len(sources)})")
        picked.append(sources[int(item)])
    if not picked:
        raise ValueError("sequences: empty selection")
    return picked


def _check_pixels(name: str, value) -> None:
    """``value`` (the option ``name``) is None or a positive finite number of pixels."""
    if value is not None and not (isinstance(value, (int, float, np.number)) and not isinstance(value, bool)
                                  and np.isfinite(value) and value > 0):
        raise ValueError(f"{name} must be a positive finite number of pixels (or None for the default), "
                         f"got {value!r}")


def _check_windows(windows) -> np.ndarray:
    """options["windows"] as (K, 2) int64 ``[t_start, t_end)`` rows: non-empty, each with
    t_end > t_start (windows may overlap, e.g. MVSEC's dt = 4 at stride 1)."""
    try:
        spans = np.asarray(windows, np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"options['windows'] must be (K, 2) [t_start, t_end) rows of integer us, got {windows!r}") from None
    if spans.ndim != 2 or spans.shape[1] != 2 or len(spans) == 0 or not np.isfinite(spans).all():
        raise ValueError(f"options['windows'] must be a non-empty (K, 2) array of [t_start, t_end) us, "
                         f"got shape {spans.shape}")
    bad = np.flatnonzero(spans[:, 1] <= spans[:, 0])
    if len(bad):
        raise ValueError(f"options['windows'] row {bad[0]} = {spans[bad[0]].astype(np.int64).tolist()}: "
                         "t_end must be > t_start")
    return spans.astype(np.int64)


def _sizes_differ(sizes: dict[str, tuple[int, int]]) -> str:
    listed = ", ".join(f"{name!r} {h}x{w}" for name, (h, w) in sizes.items())
    return (f"recordings of different sensor sizes (height x width): {listed}; an env has one frame: pass "
            "crop=(height, width) to use that crop of each, or make one env per size (scripts/evaluate.py "
            "evaluates each recording whole at its own size)")



def _loss_spec(spec: LossSpec | None, **settings) -> LossSpec:
    """The reward's spec: ``spec`` given whole, or one built from the settings given as keywords
    (None: not given, the spec's default); both at once is a ValueError."""
    given = {name: value for name, value in settings.items() if value is not None}
    if spec is None:
        return LossSpec.from_options(given)
    if not isinstance(spec, LossSpec):
        raise ValueError(f"loss_spec must be a losses.LossSpec, got {type(spec).__name__}")
    if given:
        raise ValueError(f"give the loss as loss_spec or as its settings {sorted(given)}, not both")
    return spec
