"""Test-time refinement: a policy's flow corrected by contrast maximisation on the window's own
events (``scripts/evaluate.py --refine K``; the solver: ``agents.cmax.CMaxSettings``)::

    policy = RefinedPolicy(RecurrentPolicy.from_pretrained(), steps=30)
    obs, info = env.reset()
    obs, reward, _, truncated, info = env.step(policy.act(obs, info["window"]))
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
import torch

from envs.windows import Window
from losses import unrolled_finish, window_loss, zero_flow_loss

from ..cmax import FRAME_US, CMaxSettings
from ..policy import as_flow_policy

__all__ = ["SOLVERS", "Finish", "FinishedPolicy", "RefinedPolicy", "finish_settings", "with_coarse"]

#: the refinement solvers (RefinedPolicy's docstring)
SOLVERS = ("fine", "cmax", "mid")
#: the finish training unrolls (losses/finish.py; ``--finish-steps``): a Finish's solver, not RefinedPolicy's
GRADIENT = "gd"
#: its step at lr_scale 1: TrainConfig.finish_lr's default (pixels per step per 30 Hz frame)
GRADIENT_LR = 0.3
#: the learned finish (agents/update_block.py): a Finish's solver, its steps the block's iterations
BLOCK = "block"


def gradient_finish(flow: np.ndarray, window: Window, finish: "Finish", device="cpu") -> np.ndarray:
    """``flow`` finished by ``finish.steps`` unrolled gradient steps as training takes them
    (``losses.unrolled_finish``, a 16-cell grid, step ``GRADIENT_LR * lr_scale`` x the window's
    frames), no graph; at most ``finish.max_events`` events (even subsample)."""
    if len(window.events) == 0:
        return flow
    if finish.max_events:
        window = window.subsample(finish.max_events, rounding="floor")
    frames = max(1.0, window.duration_us / FRAME_US)
    proposal = torch.as_tensor(np.asarray(flow, np.float32), device=device)[None]
    batch = window.batch(device=device)
    finished = unrolled_finish(proposal, batch, steps=finish.steps, lr=GRADIENT_LR * finish.lr_scale * frames,
                               create_graph=False)
    return finished[0].cpu().numpy()


def block_finish(flow: np.ndarray, window: Window, finish: "Finish", block, device="cpu",
                 steps: int | None = None) -> np.ndarray:
    """``flow`` finished by ``steps`` (default ``finish.steps``) iterations of the learned update
    ``block`` (``agents.update_block.learned_finish``) on at most ``finish.max_events`` events
    (even subsample), no graph."""
    from ..update_block import frames_of, learned_finish

    steps = finish.steps if steps is None else int(steps)
    if len(window.events) == 0 or steps == 0:
        return flow
    if finish.max_events:
        window = window.subsample(finish.max_events, rounding="floor")
    proposal = torch.as_tensor(np.asarray(flow, np.float32), device=device)[None]
    with torch.no_grad():
        finished = learned_finish(block, proposal, window.batch(device=device), steps=steps,
                                  frames=frames_of(window.duration_us))
    return finished[0].cpu().numpy()


def finish_settings(solver: str, steps: int, *, prior_weight: float = 0.0, max_events: int | None = None,
                    lr_scale: float = 1.0) -> CMaxSettings:
    """The solve ``solver`` (:data:`SOLVERS`) of ``steps`` steps in all, started from a base flow
    (RefinedPolicy's docstring says what each is); ``max_events``: the events it sees at most;
    ``lr_scale``: its step size times this (a short solve may need longer steps to go as far)."""
    if solver not in SOLVERS:
        raise ValueError(f"refinement solver must be one of {SOLVERS}, got {solver!r}")
    if solver == "fine":
        settings = CMaxSettings(grids=(16,), sensor_scales=(1,), steps=(steps,), lr_per_frame=0.1, lr_decay=3.0,
                                prior_weight=prior_weight)
    elif solver == "mid":
        first = round(0.5 * steps)
        settings = CMaxSettings(grids=(8, 16), sensor_scales=(2, 1), steps=(first, steps - first),
                                prior_weight=prior_weight)
    else:
        first, second = round(0.4 * steps), round(0.3 * steps)
        settings = CMaxSettings(steps=(first, second, steps - first - second), prior_weight=prior_weight)
    if lr_scale != 1.0:
        settings = dataclasses.replace(settings, lr_per_frame=settings.lr_per_frame * float(lr_scale))
    return settings if max_events is None else dataclasses.replace(settings, max_events=int(max_events))


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

    max_events: the solve runs on an even subsample of at most this many of the window's events
    (default: the solver's own bound, ``CMaxSettings.max_events``): each step costs less, the flow
    is scored on all of them.
    """

    SOLVERS = SOLVERS

    def __init__(self, policy, *, steps: int = 30, solver: str = "fine", prior_weight: float = 0.0,
                 settings: CMaxSettings | None = None, accept: float | None = None,
                 max_events: int | None = None, lr_scale: float = 1.0) -> None:
        self.policy = as_flow_policy(policy)
        if int(steps) < 0:
            raise ValueError(f"refinement steps must be >= 0, got {steps}")
        if accept is not None and not 0.0 <= accept < 1.0:
            raise ValueError(f"refinement accept must be a fraction in [0, 1), got {accept}")
        self.accept = accept
        self.accepted = 0  # windows whose refined flow was kept / refined, when gated
        self.refined = 0
        if settings is None:
            settings = finish_settings(solver, int(steps), prior_weight=prior_weight, max_events=max_events,
                                       lr_scale=lr_scale)
        elif max_events is not None:  # a cheaper step: the solve sees an even subsample of the window's events
            settings = dataclasses.replace(settings, max_events=int(max_events))
        self.settings = settings
        self.steps = sum(self.settings.steps)
        self.input_key = policy.input_key
        self.voxel_bins = policy.voxel_bins

    def reset(self, mask=None) -> None:
        self.policy.reset(mask)

    def act(self, obs, window: Window | None = None) -> np.ndarray:
        """The wrapped policy's flow, refined on the window's events (``agents.policy.FlowPolicy``)."""
        if window is None:
            raise ValueError("RefinedPolicy solves the window's events: call act(obs, window)")
        flow = self.policy.act(obs, window)
        if self.steps == 0:
            return flow
        size = tuple(flow.shape[-2:])
        refined = self.settings.solve(window, size, base=flow, device=self.policy.device)
        if self.accept is None or len(window.events) == 0:
            return refined
        batch = window.batch(device=self.policy.device)
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


@dataclass(frozen=True)
class Finish:
    """One finish of :class:`FinishedPolicy`: ``steps`` steps of ``solver`` (one of :data:`SOLVERS`,
    or :data:`GRADIENT`: the unrolled finish training takes, losses/finish.py) on at most
    ``max_events`` of the window's events (None: the solver's bound), for windows of at most
    ``up_to_frames`` 30 Hz frames (None: any length). ``coarse``: the proposal it finishes comes
    from the network on the window's events binned ``coarse`` x ``coarse`` pixels to one
    (:class:`~agents.wrappers.coarse.CoarsePolicy`; 1: on sensor pixels), which divides the
    displacements the network sees on long windows of fast motion by ``coarse``; ``splits``: that
    coarse network steps through this many equal sub-windows of the window, their flows composed.
    ``block_steps``: iterations of the learned update block (agents/update_block.py) taken on the
    proposal before the solve (0: none)."""

    solver: str
    steps: int
    max_events: int | None = None
    up_to_frames: float | None = None
    lr_scale: float = 1.0
    coarse: int = 1
    splits: int = 1
    block_steps: int = 0

    def __post_init__(self) -> None:
        for key, low, top in (("coarse", 1, 16), ("splits", 1, 64), ("block_steps", 0, 64)):
            value = getattr(self, key)
            if not isinstance(value, int) or isinstance(value, bool) or not low <= value <= top:
                raise ValueError(f"finish {self.solver}:{self.steps}: {key} must be an integer in [{low}, {top}], "
                                 f"got {value!r}")
        if self.splits > 1 and self.coarse == 1:
            raise ValueError(f"finish {self.solver}:{self.steps}: splits applies to a coarse proposal (coarse >= 2)")

    @classmethod
    def from_dict(cls, data: Mapping) -> "Finish":
        """From ``default.json``'s ``finish`` entries (ValueError naming an unknown key)."""
        unknown = set(data) - {"solver", "steps", "max_events", "up_to_frames", "lr_scale", "coarse", "splits",
                               "block_steps"}
        if unknown:
            raise ValueError(f"finish {dict(data)}: unknown keys {sorted(unknown)}")
        return cls(str(data["solver"]), int(data["steps"]), data.get("max_events"), data.get("up_to_frames"),
                   float(data.get("lr_scale", 1.0)), _whole(data.get("coarse", 1)), _whole(data.get("splits", 1)),
                   _whole(data.get("block_steps", 0)))

    def label(self) -> str:
        """``fine:3``, ``cmax:20/16000``, ``coarse3:2+cmax:20/16000``: the form scripts/tradeoff.py's modes
        use after ``net+`` (a coarse proposal: ``coarseF+...`` or ``coarseF:S+...`` instead of ``net+...``)."""
        grid = f"coarse{self.coarse}" + (f":{self.splits}" if self.splits != 1 else "") + "+"
        return ((grid if self.coarse != 1 else "") + f"{self.solver}:{self.steps}"
                + (f"/{self.max_events}" if self.max_events else "") + (f"x{self.lr_scale:g}" if self.lr_scale != 1.0 else ""))


def _whole(value):
    """A JSON number that is a whole number (3 or 3.0) as an int; anything else unchanged, for
    :class:`Finish` to refuse by name."""
    if isinstance(value, float) and value.is_integer():
        return int(value)
    return value


def with_coarse(finishes, factor: int) -> list[Finish]:
    """``finishes`` (Finish or default.json entries) with every proposal on a grid at least
    ``factor`` times coarser than the sensor's (``predict --coarse``)."""
    finishes = [f if isinstance(f, Finish) else Finish.from_dict(f) for f in finishes]
    return [dataclasses.replace(f, coarse=max(f.coarse, int(factor))) for f in finishes]


class FinishedPolicy:
    """A policy's flow (the proposal) finished by a short solve on the window's own events, the
    solve chosen by the window's length: the first of ``finishes`` whose ``up_to_frames`` the
    window does not exceed (none: the proposal unchanged). ``block``: the learned update
    (agents/update_block.py) that finishes of solver :data:`BLOCK` run. The shipped default's mode
    (``agents/weights/default.json``: ``finish``; chosen on devval, docs/finish.md): a few local
    steps on one-frame windows, where the network is near the truth and a long solve invents
    motion; the coarse-to-fine solve on longer windows, where the proposal is far off."""

    def __init__(self, policy, finishes, block=None) -> None:
        self.policy = as_flow_policy(policy)
        self.finishes = [f if isinstance(f, Finish) else Finish.from_dict(f) for f in finishes]
        if block is None and any(f.solver == BLOCK or f.block_steps for f in self.finishes):
            raise ValueError(f"finish {BLOCK}:K runs a learned update block: FinishedPolicy(..., block=...)")
        self.block = block
        self.settings = [None if f.solver in (GRADIENT, BLOCK) else
                         finish_settings(f.solver, f.steps, max_events=f.max_events, lr_scale=f.lr_scale)
                         for f in self.finishes]
        self.input_key = policy.input_key
        self.voxel_bins = policy.voxel_bins
        self.device = getattr(policy, "device", "cpu")
        self._proposers: dict[tuple[int, int], object] = {(1, 1): self.policy}
        self._last_grid: tuple[int, int] | None = None

    def reset(self, mask=None) -> None:
        for proposer in self._proposers.values():
            proposer.reset(mask)

    def proposer(self, coarse: int, splits: int = 1):
        """The policy that proposes at grid ``coarse`` (stepping ``splits`` sub-windows): the wrapped
        policy at 1; at a coarser grid a :class:`~agents.wrappers.coarse.CoarsePolicy` over a twin of
        it, which shares the network and keeps its own recurrent state (each state sees the windows
        of its own grid, so a run whose windows change length keeps both). A policy that cannot be
        twinned (not a :class:`~agents.policy.RecurrentPolicy`) is shared, and reset where the grid
        changes."""
        if (coarse, splits) not in self._proposers:
            from ..policy import RecurrentPolicy
            from .coarse import CoarsePolicy

            inner = self.policy
            if isinstance(inner, RecurrentPolicy):
                inner = RecurrentPolicy(inner.model, inner.device, input_key=inner.input_key,
                                        voxel_bins=inner.voxel_bins, autocast=inner.autocast)
            self._proposers[(coarse, splits)] = CoarsePolicy(inner, coarse, splits)
        return self._proposers[(coarse, splits)]

    def propose(self, obs, window: Window, coarse: int, splits: int = 1) -> np.ndarray:
        """The proposal at grid ``coarse``, ``splits`` sub-windows (:meth:`proposer`)."""
        proposer = self.proposer(coarse, splits)
        grid = (coarse, splits)
        last, self._last_grid = self._last_grid, grid
        if last not in (None, grid) and self._shares(grid) and self._shares(last):
            self.policy.reset()  # one state cannot carry over between grids of different sizes
        return proposer.act(obs, window)

    def _shares(self, grid: tuple[int, int]) -> bool:
        proposer = self._proposers[grid]
        return proposer is self.policy or getattr(proposer, "policy", None) is self.policy

    def finish_for(self, window: Window) -> int | None:
        """The index of the finish a window of this length gets (None: none)."""
        frames = window.duration_us / FRAME_US
        for i, finish in enumerate(self.finishes):
            if finish.up_to_frames is None or frames <= finish.up_to_frames:
                return i
        return None

    def act(self, obs, window: Window | None = None) -> np.ndarray:
        """The proposal, finished on the window's events (``agents.policy.FlowPolicy``)."""
        if window is None:
            raise ValueError("FinishedPolicy solves the window's events: call act(obs, window)")
        index = self.finish_for(window)
        grid = (1, 1) if index is None else (self.finishes[index].coarse, self.finishes[index].splits)
        flow = self.propose(obs, window, *grid)
        if index is not None and self.finishes[index].block_steps:
            flow = block_finish(flow, window, self.finishes[index], self.block, self.device,
                                steps=self.finishes[index].block_steps)
        if index is None or self.finishes[index].steps == 0:
            return flow
        if self.finishes[index].solver == BLOCK:
            return block_finish(flow, window, self.finishes[index], self.block, self.device)
        if self.settings[index] is None:  # the training's unrolled finish, without its graph
            return gradient_finish(flow, window, self.finishes[index], self.device)
        return self.settings[index].solve(window, tuple(flow.shape[-2:]), base=flow, device=self.device)
