"""Test-time refinement: a policy's flow corrected by contrast maximisation on the window's own
events (``scripts/evaluate.py --refine K``; the solver: ``agents.cmax.CMaxSettings``)::

    policy = RefinedPolicy(RecurrentPolicy.from_pretrained(), steps=30)
    obs, info = env.reset()
    obs, reward, _, truncated, info = env.step(policy.act(obs, info["window"]))
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
import torch

from losses import EventBatch, window_loss, zero_flow_loss

from ..cmax import CMaxSettings
from ..policy import as_flow_policy

__all__ = ["RefinedPolicy"]


class RefinedPolicy:
    """A policy's flow refined by contrast maximisation on the window's own events.

    The solve optimises a coarse residual grid added to the network's flow (so the network's
    detail stays); ``steps = 0`` returns the network's flow unchanged. The refinement does not
    feed back into the network (its state carries its own prediction, as without refinement).
    solver: "fine", one 16-cell level on sensor pixels of ``steps`` Adam steps (0.1 px per frame,
    decaying 3x): a local correction; "cmax", the ``--cmax`` row's coarse-to-fine solve (4-8-16
    cells on 4x-2x-1x coarser sensor grids, its step size) started from the network's flow,
    ``steps`` shared 40/30/30 among the levels: it can move as far as the solve from zero, and
    starts nearer the truth wherever the network is; "mid", that solve's two finer levels only
    (8-16 cells on 2x-1x sensor grids, ``steps`` shared 50/50): the proposal is trusted for the
    coarse motion and corrected at the scales it gets wrong. prior_weight: how strongly the solve is held
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

    SOLVERS = ("fine", "cmax", "mid")

    def __init__(self, policy, *, steps: int = 30, solver: str = "fine", prior_weight: float = 0.0,
                 settings: CMaxSettings | None = None, accept: float | None = None) -> None:
        self.policy = as_flow_policy(policy)
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
        elif settings is None and solver == "mid":
            first = round(0.5 * int(steps))
            settings = CMaxSettings(grids=(8, 16), sensor_scales=(2, 1), steps=(first, int(steps) - first),
                                    prior_weight=prior_weight)
        elif settings is None:
            first, second = round(0.4 * int(steps)), round(0.3 * int(steps))
            settings = CMaxSettings(steps=(first, second, int(steps) - first - second), prior_weight=prior_weight)
        self.settings = settings
        self.steps = sum(self.settings.steps)
        self.input_key = policy.input_key
        self.voxel_bins = policy.voxel_bins

    def reset(self, mask=None) -> None:
        self.policy.reset(mask)

    def act(self, obs, window: Mapping | None = None) -> np.ndarray:
        """The wrapped policy's flow, refined on the window's events (``agents.policy.FlowPolicy``)."""
        if window is None:
            raise ValueError("RefinedPolicy solves the window's events: call act(obs, window)")
        flow = self.policy.act(obs, window)
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
