"""Policies that solve each window by contrast maximisation (no network, no ground truth), and
test-time refinement of a network's flow by the same solver.

Both act on a window's *events*, not only on its observation image, so they take the window
too: ``flow = policy.act_on_window(observation, window)`` with ``window`` the env's
``info["window"]`` (or any window dict of numpy ``x, y, t, p`` and ints ``t_start, t_end``).
:func:`agents.evaluation.evaluate` and ``scripts/evaluate.py`` (``--cmax``, ``--refine K``)
use them; in an env loop::

    policy = RefinedPolicy(RecurrentPolicy.from_pretrained(), steps=30)
    obs, info = env.reset()
    obs, reward, _, truncated, info = env.step(policy.act_on_window(obs, info["window"]))

The solver is :func:`losses.contrast_maximisation_flow`: a coarse grid of flow vectors,
bilinearly upsampled, optimised with Adam on L_HMC (with the env's border rule) of the window's
events; coarse to fine in flow cells and in sensor pixels.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import asdict, dataclass, field

import numpy as np
import torch

from losses import CMAX_WEIGHTS, EventBatch, LossWeights, contrast_maximisation_flow, window_loss, zero_flow_loss

__all__ = ["CMaxSettings", "ContrastMaximisationPolicy", "RefinedPolicy", "FRAME_US"]

#: The step size is given per 30 Hz frame of window length: a longer window moves further.
FRAME_US = 33_333


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

    @property
    def weights(self) -> LossWeights:
        """The loss weights of the solve."""
        return LossWeights(self.lambda_1, self.lambda_2, self.alpha, self.border_penalty, self.border_ramp)

    def solve(self, window: Mapping, size: tuple[int, int], base: np.ndarray | None = None,
              device: str | torch.device = "cpu") -> np.ndarray:
        """(2, H, W) float32 flow in pixels over ``window`` (the env's ``info["window"]``, or a
        dict of x, y, t, p, t_start, t_end).
        ``base``: optional (2, H, W) flow that the solve corrects (default: solve from zero)."""
        height, width = size
        n = len(window["t"])
        if n == 0:
            return np.zeros((2, height, width), np.float32) if base is None else np.asarray(base, np.float32)
        if n > self.max_events:
            pick = np.linspace(0, n - 1, self.max_events).astype(np.int64)
            window = {**{k: np.asarray(window[k])[pick] for k in ("x", "y", "t", "p")},
                      "t_start": window["t_start"], "t_end": window["t_end"]}
        batch = EventBatch.from_windows([window], device=device)
        frames = max(1.0, (int(window["t_end"]) - int(window["t_start"])) / FRAME_US)
        offset = None if base is None else torch.as_tensor(np.asarray(base, np.float32), device=device)[None]
        flow = contrast_maximisation_flow(
            batch, height, width, grids=self.grids, steps=self.steps, lr=self.lr_per_frame * frames,
            sensor_scales=self.sensor_scales, lr_decay=self.lr_decay, flow_scaling=self.flow_scaling,
            weights=self.weights, base=offset, prior_weight=self.prior_weight if base is not None else 0.0,
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

    def act_on_window(self, obs, window: Mapping) -> np.ndarray:
        size = tuple(np.asarray(obs[self.input_key]).shape[-2:])
        return self.settings.solve(window, size, device=self.device)


class RefinedPolicy:
    """A recurrent policy's flow refined by contrast maximisation on the window's own events.

    The solve optimises a coarse residual grid added to the network's flow (so the network's
    detail stays); ``steps = 0`` returns the network's flow unchanged. The refinement does not
    feed back into the network (its state carries its own prediction, as without refinement).
    solver: "fine", one 16-cell level on sensor pixels of ``steps`` Adam steps (0.1 px per frame,
    decaying 3x): a local correction; "cmax", the ``--cmax`` row's coarse-to-fine solve (4-8-16
    cells on 4x-2x-1x coarser sensor grids, its step size) started from the network's flow,
    ``steps`` shared 40/30/30 among the levels: it can move as far as the solve from zero, and
    starts nearer the truth wherever the network is. prior_weight: how strongly the solve is held
    to the network's flow (``CMaxSettings.prior_weight``). settings: any other solve (its steps
    and prior then override ``steps`` and ``prior_weight``).

    accept: keep the refined flow only where it lowers the window's loss as the env scores it
    (``losses.window_loss``: L_HMC, paper weights, with the border rule; flow scaling max(H, W))
    by at least the fraction ``accept`` of the network's; otherwise the network's flow stays
    (None: always the refined flow; 0: the refined flow unless it raises that loss). The idea:
    where the network is near the truth the solve still finds a slightly lower loss by inventing
    motion, a small drop. Whether a drop says where the refinement helps is measured, per split,
    by ``tools/refine_gate.py`` (docs/history/2026-12-02-round-11.md).
    """

    SOLVERS = ("fine", "cmax")

    def __init__(self, policy, *, steps: int = 30, solver: str = "fine", prior_weight: float = 0.0,
                 settings: CMaxSettings | None = None, accept: float | None = None) -> None:
        self.policy = policy
        if int(steps) < 0:
            raise ValueError(f"refinement steps must be >= 0, got {steps}")
        if accept is not None and not 0.0 <= accept < 1.0:
            raise ValueError(f"refinement accept must be a fraction in [0, 1), got {accept}")
        self.accept = accept
        self.accepted = 0  # windows whose refined flow was kept / refined, when gated
        self.refined = 0
        if solver not in self.SOLVERS:
            raise ValueError(f"refinement solver must be one of {self.SOLVERS}, got {solver!r}")
        if settings is None and solver == "fine":
            settings = CMaxSettings(grids=(16,), sensor_scales=(1,), steps=(int(steps),), lr_per_frame=0.1,
                                    lr_decay=3.0, prior_weight=prior_weight)
        elif settings is None:
            first, second = round(0.4 * int(steps)), round(0.3 * int(steps))
            settings = CMaxSettings(steps=(first, second, int(steps) - first - second), prior_weight=prior_weight)
        self.settings = settings
        self.steps = sum(self.settings.steps)
        self.input_key = policy.input_key
        self.voxel_bins = policy.voxel_bins

    def reset(self, mask=None) -> None:
        self.policy.reset(mask)

    def act_on_window(self, obs, window: Mapping) -> np.ndarray:
        inner = getattr(self.policy, "act_on_window", None)  # e.g. a SubWindowPolicy
        flow = inner(obs, window) if inner is not None else self.policy.act(obs)
        if self.steps == 0:
            return flow
        size = tuple(flow.shape[-2:])
        refined = self.settings.solve(window, size, base=flow, device=self.policy.device)
        if self.accept is None or len(window["t"]) == 0:
            return refined
        batch = EventBatch.from_windows([window], device=self.policy.device)
        flows = [torch.as_tensor(f, device=self.policy.device)[None] for f in (flow, refined)]
        scale = float(max(size))
        zero = zero_flow_loss(flows[0], batch, flow_scaling=scale).per_sample  # the border rule's, once for both
        with torch.no_grad():
            before, after = (float(window_loss(f, batch, flow_scaling=scale, zero_flow=zero).loss) for f in flows)
        self.refined += 1
        if after <= (1.0 - self.accept) * before:
            self.accepted += 1
            return refined
        return flow
