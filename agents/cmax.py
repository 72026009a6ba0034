"""A policy that solves each window by contrast maximisation (no network, no ground truth), and
the solve it runs, which the test-time refinement of a network's flow
(``agents.wrappers.refine.RefinedPolicy``, ``--refine K``) runs too.

It acts on a window's *events*, not on its observation image, so it needs the window:
``flow = policy.act(observation, window)`` with ``window`` the env's ``info["window"]`` (or any
window dict of numpy ``x, y, t, p`` and ints ``t_start, t_end``).
:func:`agents.evaluation.evaluate` and ``scripts/evaluate.py --cmax`` use it; in an env loop::

    policy = ContrastMaximisationPolicy()
    obs, info = env.reset()
    obs, reward, _, truncated, info = env.step(policy.act(obs, info["window"]))

The solver is :func:`losses.contrast_maximisation_flow`: a coarse grid of flow vectors,
bilinearly upsampled, optimised with Adam on L_HMC (with the env's border rule) of the window's
events; coarse to fine in flow cells and in sensor pixels.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

import numpy as np
import torch

from envs.windows import FALLBACK_INTERVAL_US, Window
from losses import CMAX_WEIGHTS, LossSpec, contrast_maximisation_flow

__all__ = ["CMaxSettings", "ContrastMaximisationPolicy", "EVIDENCE_PRIOR", "FRAME_US"]

#: The step size is given per 30 Hz frame of window length: a longer window moves further.
FRAME_US = FALLBACK_INTERVAL_US

#: ``CMaxSettings.evidence_prior`` as measured (docs/history/2026-12-05-round-15.md, "Still scenes and the solve"):
#: a window of 30,000 events is held to zero flow with weight 1.
EVIDENCE_PRIOR = 30_000.0


def check_solver_settings(settings, name: str) -> None:
    """ValueError naming the field when a contrast-maximisation solve's settings cannot run
    (``CMaxSettings``, ``agents.teacher.TeacherSettings``): found where they are made, not
    after a run has started and written its configuration."""
    levels = len(tuple(settings.grids))
    if levels == 0 or any(int(g) < 1 for g in settings.grids):
        raise ValueError(f"{name}: grids must be positive cell counts, got {settings.grids}")
    per_level = isinstance(settings.steps, (tuple, list))
    steps = tuple(settings.steps) if per_level else (settings.steps,)
    if any(int(k) < 0 for k in steps) or (per_level and len(steps) != levels):
        raise ValueError(f"{name}: steps must be one count >= 0 or one per grid level ({levels}), "
                         f"got {settings.steps}")
    scales = settings.sensor_scales
    if scales is not None and (len(tuple(scales)) != levels or any(int(v) < 1 for v in scales)):
        raise ValueError(f"{name}: sensor_scales must be one positive factor per grid level ({levels}), got {scales}")
    for field_name in ("lr_per_frame", "lr_decay", "flow_scaling"):
        value = float(getattr(settings, field_name))
        if not np.isfinite(value) or value <= 0:
            raise ValueError(f"{name}: {field_name} must be a positive number, got {value}")
    for field_name in ("evidence_prior", "prior_weight"):
        value = float(getattr(settings, field_name, 0.0))
        if not np.isfinite(value) or value < 0:
            raise ValueError(f"{name}: {field_name} must be >= 0, got {value}")


@dataclass(frozen=True)
class CMaxSettings:
    """One per-window contrast-maximisation solve.

    grids: flow cells along the longer side per level (coarse to fine).
    sensor_scales: sensor-grid coarsening per level (events splatted at x / s; 1 = sensor pixels).
    steps: Adam steps per level. lr_per_frame: Adam's step size in pixels, times the window's
    length in 30 Hz frames. lr_decay: the step size falls by this factor over the run.
    The loss weights are those of the env's reward except lambda_2 (a stronger smoothness term
    regularises the coarse grid) and a fixed flow_scaling (pixels per unit in that term).
    max_events: windows with more events are solved on an even subsample (cost bound).
    prior_weight: with a base flow (refinement), the weight of the residual's mean square in
    flow-scaling units (``losses.contrast_maximisation_flow``); 0: none.
    evidence_prior: a prior toward the starting flow (zero flow, or the base) whose weight is
    ``evidence_prior / events in the window`` (added to prior_weight): a window with few events
    keeps still unless they demand motion; one with many is solved as without it. 0: none
    (``EVIDENCE_PRIOR`` is the measured setting, docs/history/2026-12-05-round-15.md).
    """

    grids: tuple[int, ...] = (4, 8, 16)
    sensor_scales: tuple[int, ...] = (4, 2, 1)
    steps: tuple[int, ...] = (40, 30, 30)
    lr_per_frame: float = 0.3
    lr_decay: float = 10.0
    lambda_1: float = CMAX_WEIGHTS.lambda_1
    lambda_2: float = CMAX_WEIGHTS.lambda_2
    alpha: float = CMAX_WEIGHTS.alpha
    border_penalty: float = CMAX_WEIGHTS.border_penalty
    border_ramp: float = CMAX_WEIGHTS.border_ramp
    flow_scaling: float = 32.0
    max_events: int = 60_000
    prior_weight: float = 0.0
    evidence_prior: float = 0.0

    @property
    def loss_spec(self) -> LossSpec:
        """The loss of the solve (losses.LossSpec, from the fields that bear its settings' names)."""
        return LossSpec.from_options(self)

    @property
    def weights(self) -> LossSpec:
        """:attr:`loss_spec` under its earlier name."""
        return self.loss_spec

    def __post_init__(self) -> None:
        check_solver_settings(self, "CMaxSettings")
        if self.max_events < 1:
            raise ValueError(f"CMaxSettings: max_events must be >= 1, got {self.max_events}")

    def solve(self, window: Window, size: tuple[int, int], base: np.ndarray | None = None,
              device: str | torch.device = "cpu") -> np.ndarray:
        """(2, H, W) float32 flow in pixels over ``window`` (the env's ``info["window"]``, a
        :class:`~envs.windows.Window`).
        ``base``: optional (2, H, W) flow that the solve corrects (default: solve from zero)."""
        height, width = size
        n = len(window.events)
        if n == 0:
            return np.zeros((2, height, width), np.float32) if base is None else np.asarray(base, np.float32)
        prior = (self.prior_weight if base is not None else 0.0) + self.evidence_prior / n
        window = window.subsample(self.max_events, rounding="floor")
        batch = window.batch(device=device)
        frames = max(1.0, window.duration_us / FRAME_US)
        offset = None if base is None else torch.as_tensor(np.asarray(base, np.float32), device=device)[None]
        flow = contrast_maximisation_flow(
            batch, height, width, grids=self.grids, steps=self.steps, lr=self.lr_per_frame * frames,
            sensor_scales=self.sensor_scales, lr_decay=self.lr_decay, flow_scaling=self.flow_scaling,
            weights=self.loss_spec, base=offset, prior_weight=prior,
        )
        return flow[0].cpu().numpy().astype(np.float32)

    def describe(self) -> dict:
        return asdict(self)


#: The plain coarse-to-fine solve on sensor pixels (the teacher targets' solver).
PLAIN = CMaxSettings(sensor_scales=(1, 1, 1), steps=(40, 40, 40), lr_per_frame=0.05, lr_decay=1.0)


@dataclass
class ContrastMaximisationPolicy:
    """Per-window contrast maximisation as a policy: no network, no state, no ground truth."""

    settings: CMaxSettings = field(default_factory=CMaxSettings)
    device: str = "cpu"
    input_key: str = "count_image"
    voxel_bins: int = 5

    def reset(self, mask=None) -> None:
        """Nothing to reset: every window is solved on its own."""

    def act(self, obs, window: Window | None = None) -> np.ndarray:
        """The window's flow solved from its events (``agents.policy.FlowPolicy``)."""
        if window is None:
            raise ValueError("ContrastMaximisationPolicy solves the window's events: call act(obs, window)")
        size = tuple(np.asarray(obs[self.input_key]).shape[-2:])
        return self.settings.solve(window, size, device=self.device)

