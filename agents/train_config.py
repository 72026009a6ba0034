"""The configuration of a training run (:class:`TrainConfig`, saved in every checkpoint as a
dict) and its named recipes (``PRESETS``). Its own module, below the learner and the objectives
that read it (agents/learner.py re-exports the names)."""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass
from typing import Any, Literal

from envs.env import check_event_keep
from envs.representations import OBSERVATIONS
from losses import CMAX_WEIGHTS, LossSpec

from .options import (
    ModelWidth,
    SensorSizeOptions,
    Windows,
    check_choices,
    keep_fraction,
    non_negative_float,
    non_negative_int,
    one_or_list,
    option,
    positive_float,
    positive_int,
    to_argv,
    torch_device,
)

__all__ = ["TrainConfig", "PRESETS", "preset_config", "preset_options"]

#: The choices of ``--input`` (TrainConfig.input): the image observations of envs.representations.OBSERVATIONS.
ImageInput = Literal[tuple(OBSERVATIONS)]


def _key_values(items) -> dict:
    """``KEY=VALUE`` items (VALUE read as JSON where it parses) as a dict; a dict passes unchanged."""
    if isinstance(items, dict):
        return items
    out = {}
    for item in items or []:
        key, sep, value = item.partition("=")
        if not sep:
            raise ValueError(f"--model-kwarg expects key=value, got {item!r}")
        try:
            out[key] = json.loads(value)
        except json.JSONDecodeError:
            out[key] = value
    return out


@dataclass
class TrainConfig(ModelWidth, Windows, SensorSizeOptions):
    """Everything a training run depends on (saved in every checkpoint). Each field is one option
    of ``scripts/train.py`` (agents/options.py writes the command line from this class); the
    string under a field is its help. ``width``, the windows (``window``, ``window_size``) and
    ``sensor_size`` are option groups the commands share (agents.options)."""

    model: str = "ev-mgrflownet"
    """registry name (ev-mgrflownet, ev-flownet, convgru-ev-flownet, xlif-ev-flownet, unet-*) or pkg.module:factory"""
    model_kwargs: dict = option(flag="--model-kwarg", action="append", metavar="KEY=VALUE", convert=_key_values,
                                default_factory=dict)
    """extra model argument, e.g. use_st_convgru=false (repeatable)"""
    input: ImageInput = "count_image"
    """the paper's count image (eq. 2), a voxel grid (--voxel-bins), or EV-FlowNet's counts and timestamps"""
    voxel_bins: int = option(5, type=positive_int)
    """time bins of the voxel-grid input"""
    data: Any = option("synthetic-train", nargs="+", convert=one_or_list)
    """synthetic split name, recording files or directories"""
    crop: tuple[int, ...] | None = option(None, type=non_negative_int)
    """H W (centred) or TOP LEFT H W"""
    random_crop: bool = False
    """place the --crop H W window at a random position in each episode (validation uses whole frames)"""
    flips: bool = True
    """Hagenaars' random h/v/polarity flips, once per sequence (--no-flips: off)"""
    event_keep: tuple[float, ...] | None = option(None, type=keep_fraction, metavar="P")
    """thin the training events: keep each with probability P, or (LOW HIGH) with one drawn per episode log-uniformly in the range; the motion and its targets are unchanged, so the event density stops telling the speed"""
    num_envs: int = option(4, type=positive_int)
    """B, sequences rolled out in parallel"""
    vector: Literal["sync", "async"] = "sync"
    """gymnasium vector env: in this process or in worker processes"""
    unroll: int = option(10, type=positive_int)
    """L, windows per truncated-BPTT update (paper: 10)"""
    steps: int = option(1000, type=non_negative_int)
    """total optimizer steps (0: save the starting weights, e.g. of --init, as a new run)"""
    lr: float = option(1e-4, type=non_negative_float)
    """Adam step size (paper)"""
    warmup_steps: int = option(0, type=non_negative_int)
    """steps of linear warm-up of the step size"""
    decay: Literal["none", "cosine"] = "none"
    """step-size decay over --steps"""
    grad_clip: float = option(100.0, type=positive_float)
    """gradient norm clip (Hagenaars)"""
    moment_warmup: int = option(50, type=non_negative_int)
    """steps of linear warm-up after a resume whose state holds no Adam moments (a campaign's slim state)"""
    loss: Literal["hmc", "at", "teacher", "supervised"] = "hmc"
    """hmc (paper), at (baseline), teacher (regress per-window contrast maximisation), supervised (a reference)"""
    loss_mode: Literal["window", "accumulated"] = "window"
    """window: the mean of the L windows' losses; accumulated: one loss over all L (Hagenaars' sequential learning)"""
    # The loss readings the paper leaves open (docs/method.md).
    loss_scales: Literal["all", "finest"] = "all"
    """all: every decoder scale's flow in the loss, averaged; finest: the full-resolution flow only"""
    upsampling: Literal["bilinear", "nearest"] = "bilinear"
    """how coarse scales' flows reach full resolution in the loss"""
    reference_times: Literal["window", "events"] = "window"
    """window: references at the window bounds; events: at the first and last event"""
    at_normalisation: Literal["event_pixels", "sum"] = "event_pixels"
    """L_AT over the pixels holding events, or sum: eq. 14's bare sum"""
    lambda_1: float = option(LossSpec.lambda_1, type=non_negative_float)
    """weight of the event-count term in L_HMC (eq. 17)"""
    lambda_2: float = option(LossSpec.lambda_2, type=non_negative_float)
    """weight of the smoothness term (eq. 17)"""
    alpha: float = option(LossSpec.alpha, type=positive_float)
    """exponent of the event-count term (eqs. 15-16)"""
    border_penalty: float = LossSpec.border_penalty
    """border rule weight: x zero-flow loss x share of events pushed out of the image (0: the paper's loss)"""
    border_ramp: float = LossSpec.border_ramp
    """border rule ramp: an event d px beyond the image pays min(1, d / ramp) of its share (0: all of it)"""
    flow_scaling: float | None = option(None, type=positive_float)
    """pixels per network unit (default max(H, W))"""
    teacher_grids: tuple[int, ...] = option((4, 8), type=positive_int)
    """teacher: coarse-to-fine grid cells along the longer side"""
    teacher_steps: int = option(40, type=positive_int)
    """teacher: Adam steps per level"""
    teacher_lr: float = option(0.05, type=positive_float)
    """teacher: Adam step size (pixels)"""
    teacher_lambda_2: float = option(CMAX_WEIGHTS.lambda_2, type=non_negative_float)
    """teacher: smoothness weight"""
    teacher_pixels: Literal["events", "all"] = "events"
    """teacher: regress on pixels holding events, or on every pixel"""
    teacher_max_events: int | None = option(None, type=positive_int)
    """teacher: solve on at most this many events per window, evenly subsampled (default: all)"""
    teacher_cache: str | None = None
    """teacher: precomputed targets (scripts/teacher_targets.py) instead of solving every update"""
    finish_steps: int = option(0, type=non_negative_int)
    """take the loss after K unrolled gradient steps of the window's L_HMC on the finest flow (losses/finish.py): the network trained as the proposal a short solve finishes (docs/finish.md); 0: none"""
    finish_lr: float = option(0.3, type=positive_float)
    """the unrolled finish's step: the mean move of a correction cell in pixels, times the window's length in 30 Hz frames"""
    finish_grid: int = option(16, type=positive_int)
    """the unrolled finish's correction grid: cells along the longer side"""
    head_init: float | None = option(None, metavar="A", type=non_negative_float)
    """re-draw the flow heads' weights from U(-A, A), biases 0 (start near zero flow)"""
    seed: int = option(0, type=non_negative_int)
    """seeds the initial weights, the episodes and the flips"""
    device: str = option("cpu", type=torch_device)
    """torch device"""
    amp: Literal["auto", "bf16", "fp16", "off"] = "auto"
    """mixed precision of the network's forward (losses stay float32): auto = bf16 on a CUDA device that supports it, else off; fp16: CUDA only"""

    def __post_init__(self) -> None:
        check_choices(self)
        if self.loss == "at" and self.loss_mode == "accumulated":  # it would train L_HMC without saying so
            raise ValueError("--loss-mode accumulated is one L_HMC over the L windows (Hagenaars' sequential "
                             "learning) and exists for --loss hmc alone: --loss at takes --loss-mode window")
        if self.finish_steps and self.loss_mode == "accumulated" and self.loss in ("hmc", "at"):
            raise ValueError("--finish-steps finishes each window's flow: it needs --loss-mode window (or a teacher)")
        if self.event_keep is not None:  # refused where the options are read, not when the envs are built
            try:
                keep = check_event_keep(self.event_keep)
            except ValueError as err:
                raise ValueError(f"--event-keep: {err}") from None
            self.event_keep = None if keep is None else keep[:1] if keep[0] == keep[1] else keep

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    @property
    def loss_spec(self) -> LossSpec:
        """The loss of this run (losses.LossSpec, built from the fields that bear its settings'
        names): L_AT with ``loss="at"``, else L_HMC (what the teacher and supervised runs log)."""
        return LossSpec.from_options(self, loss="at" if self.loss == "at" else "hmc")

    @property
    def weights(self) -> LossSpec:
        """:attr:`loss_spec` under its earlier name."""
        return self.loss_spec


_RECIPE = {"model": "ev-mgrflownet", "width": "cpu", "input": "voxel_grid", "crop": (64, 64), "random_crop": True,
           "flow_scaling": 32.0, "num_envs": 8, "unroll": 4}

#: Named recipes: TrainConfig values a preset sets (options given beside it still win).
PRESETS: dict[str, dict[str, Any]] = {
    # Zhuang et al. 2024, sec. IV-A: EV-MGRFlowNet at the paper's width on count images, all four
    # scales' flows in the loss, Adam at 1e-4, L = 10 windows per update, and L_HMC over those
    # windows as Hagenaars' sequential learning (one loss over the events of all L windows,
    # references 0 and L). The border rule stays on (docs/method.md says why; --border-penalty 0
    # gives the paper's bare loss).
    "paper": {
        "model": "ev-mgrflownet", "width": "paper", "input": "count_image", "lr": 1e-4, "unroll": 10,
        "loss": "hmc", "loss_mode": "accumulated", "loss_scales": "all", "lambda_1": LossSpec.lambda_1,
        "lambda_2": LossSpec.lambda_2, "alpha": LossSpec.alpha, "grad_clip": 100.0, "decay": "none",
        "warmup_steps": 0,
    },
    # The project's recipe (docs/results.md), stage 1: distil the per-window contrast-maximisation
    # teacher of L_HMC from targets solved once (scripts/teacher_targets.py); the shipped
    # ev-mgrflownet-cpu-synthetic was trained this way (its provenance gives the command).
    "teacher-cached": {**_RECIPE, "loss": "teacher", "teacher_cache": "runs/teacher-targets/train.h5",
                       "teacher_pixels": "all", "window_size": [1, 2, 3, 4], "lr": 1e-3, "head_init": 0.1},
    # stage 1 solving the teacher inside every update (no wait for the targets: the main job's demo)
    "teacher": {**_RECIPE, "loss": "teacher", "window_size": [1, 2, 3, 4], "lr": 1e-3, "head_init": 0.1,
                "teacher_steps": 20, "teacher_pixels": "all", "teacher_max_events": 8000},
    # stage 2: the paper's per-window L_HMC (the env's reward, ramped border rule) from stage 1
    # (ev-mgrflownet-cpu-synthetic-hmc's provenance)
    "hmc-stage": {**_RECIPE, "loss": "hmc", "window_size": 4, "lr": 3e-4},
}


def preset_config(name: str, **overrides) -> TrainConfig:
    """The TrainConfig of preset ``name`` with ``overrides`` on top."""
    if name not in PRESETS:
        raise ValueError(f"unknown preset {name!r}; presets: {sorted(PRESETS)}")
    return TrainConfig(**{**PRESETS[name], **overrides})


def preset_options(name: str) -> list[str]:
    """The scripts/train.py options that spell out preset ``name``."""
    return to_argv(TrainConfig, PRESETS[name])
