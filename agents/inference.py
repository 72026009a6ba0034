"""Flow for events in memory, in one call: the default model in its mode (the network's proposal
finished by a short solve on each window's events, docs/finish.md) over fixed time windows::

    import numpy as np
    from agents import predict_flow

    events = np.load("events.npy")                     # structured: x, y, t (µs), p  (tonic's layout)
    flows, bounds = predict_flow(events, sensor_size=(480, 640))
    # flows: (K, 2, 480, 640) float32, pixels of displacement over each window
    # bounds: (K, 2) int64 µs, each window's [t_start, t_end)

For files, the command ``scripts/predict.py`` does the same and writes the flow, a preview and a
table.
"""

from __future__ import annotations

import numpy as np

from envs.env import EventFlowEnv
from envs.windows import FALLBACK_INTERVAL_US

from .policy import RecurrentPolicy
from .rollout import observation_options

__all__ = ["predict_flow"]


def predict_flow(events, sensor_size=None, *, window_us: int = FALLBACK_INTERVAL_US, model: str | None = None,
                 finish: bool = True, device: str = "cpu", max_windows: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The flow of every ``window_us`` window of ``events`` (a structured array with fields x, y,
    t, p, t in µs; a mapping of those arrays; ``Events``; or a recording path), as (flows (K, 2,
    H, W) float32 pixels per window, bounds (K, 2) int64 µs). sensor_size: (height, width),
    tonic's (width, height, polarities) or "auto" (events only; a file gives its own). model: a
    shipped name (default: the default); finish: the default's short solve on each window (the
    default model only; False: the network's proposal alone, faster). max_windows: the first K."""
    from .pretrained import default_finish
    from .wrappers.refine import FinishedPolicy

    policy = RecurrentPolicy.from_pretrained(model, device=device)
    finishes = default_finish() if finish and model is None else []
    actor = FinishedPolicy(policy, finishes) if finishes else policy
    env = EventFlowEnv(events, sensor_size=sensor_size, window="time", window_size=int(window_us),
                       compute_reward=False, **observation_options(policy))
    flows, bounds = [], []
    try:
        obs, info = env.reset(options={"sequence": 0})
        actor.reset()
        while True:
            window = info["window"]
            flow = actor.act(obs, window)
            flows.append(np.asarray(flow, np.float32))
            bounds.append((int(window.t_start), int(window.t_end)))
            if max_windows is not None and len(flows) >= max_windows:
                break
            obs, _, terminated, truncated, info = env.step(flow)
            if terminated or truncated:
                break
    finally:
        env.close()
    height, width = env.height, env.width
    return (np.stack(flows) if flows else np.zeros((0, 2, height, width), np.float32),
            np.asarray(bounds, np.int64).reshape(-1, 2))
