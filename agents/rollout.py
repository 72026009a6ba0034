"""One rollout: a flow policy driven through an EventFlow env window by window, the loop the
evaluation, predict and the teacher share::

    env = EventFlowEnv("synthetic-mini", compute_reward=False, **observation_options(policy))
    for step in rollout(policy, env, options={"sequence": 0}):
        print(step.window, step.flow.shape, step.seconds)

A rollout is one sequence (one env episode): the env is reset with ``options``, the policy's
recurrent state is reset with it (every sequence starts fresh), and then each window's flow,
``policy.act(obs, window)`` (``agents.policy.FlowPolicy``; a plug-in's ``act(obs)`` is adapted),
is the env's action for that window, which carries the state on to the next one.
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np

from envs.env import EventFlowEnv
from envs.windows import Window

from .policy import FlowPolicy, as_flow_policy

__all__ = ["WindowStep", "rollout", "observation_options"]


@dataclass(frozen=True)
class WindowStep:
    """One window of a rollout, after the env stepped on its flow.

    index: the window's place in the rollout, from 0. obs: the observation the policy acted on;
    info: the env's info that came with it (``info["window"]`` is ``window``; ``flow_gt`` /
    ``flow_gt_valid`` where there is ground truth, ``sequence``, ``crop``, ...). window: the
    window (``envs.windows.Window``). flow: (2, H, W) float32 pixels of displacement over the
    window, the policy's action. reward: the env's reward for it (-L_HMC; 0.0 when the env
    computes none). seconds: the time ``policy.act`` took.
    """

    index: int
    obs: dict[str, np.ndarray]
    info: dict[str, Any]
    window: Window
    flow: np.ndarray
    reward: float
    seconds: float


def rollout(policy: FlowPolicy, env: EventFlowEnv, *, options: dict | None = None,
            max_windows: int | None = None) -> Iterator[WindowStep]:
    """Roll ``policy`` through one sequence of ``env``: a :class:`WindowStep` per window, in order,
    up to the sequence's end or ``max_windows`` windows.

    The env and the policy are reset here, at the call (so a recording without a window raises
    ``envs.env.NoWindowsError`` from this call, not from the loop over its steps): ``options`` go
    to ``env.reset`` (e.g. ``{"sequence": 0, "windows": bounds}``). The windows come as the steps
    are taken; a caller that stops early leaves the rest unread.
    """
    policy = as_flow_policy(policy)
    obs, info = env.reset(options=options)
    policy.reset()
    return _steps(policy, env, obs, info, max_windows)


def _steps(policy: FlowPolicy, env: EventFlowEnv, obs, info, max_windows: int | None) -> Iterator[WindowStep]:
    index, truncated = 0, False
    while not truncated and (max_windows is None or index < max_windows):
        window = info["window"]
        began = time.perf_counter()
        flow = policy.act(obs, window)
        seconds = time.perf_counter() - began
        next_obs, reward, _, truncated, next_info = env.step(flow)
        yield WindowStep(index, obs, info, window, flow, float(reward), seconds)
        obs, info, index = next_obs, next_info, index + 1


def observation_options(policy) -> dict[str, Any]:
    """The env's ``observations`` and ``voxel_bins`` for ``policy``: the count image (which the
    pictures and previews draw) and the part the policy reads (its ``input_key``, default the
    count image), of ``voxel_bins`` bins when a voxel grid (default 5)."""
    key = getattr(policy, "input_key", "count_image")
    parts = ("count_image",) if key == "count_image" else ("count_image", key)
    return {"observations": parts, "voxel_bins": getattr(policy, "voxel_bins", 5)}
