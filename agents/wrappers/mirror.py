"""Test-time mirroring: a recurrent policy's flow averaged over mirrored copies of its input.

The networks are trained on recordings flipped left-right and up-down at random (the env's
``flips``), so a mirrored recording is as familiar to them as the original. Running the network
on the input, its left-right mirror, its up-down mirror and both, mirroring each flow back
(the x component changes sign under a left-right mirror, y under an up-down one) and averaging
the four gives a flow whose independent errors partly cancel, at four network steps per window::

    policy = MirrorPolicy(RecurrentPolicy.from_pretrained())
    flow = policy.act(obs)

Each mirror keeps its own recurrent state (a mirrored sequence is a sequence of its own).
Half the cost: ``MirrorPolicy(policy, ROTATION)``, the input and its rotation by 180 degrees
(left-right and up-down at once), two network steps per window.
``scripts/evaluate.py --mirror`` adds a row per model (``--mirror 2``: the rotation pair; with
``--split``, the split rows are mirrored too).
"""

from __future__ import annotations

import numpy as np

from envs.windows import Window

__all__ = ["MirrorPolicy", "MIRRORS", "ROTATION", "MIRROR_SETS"]

#: (left-right, up-down) per copy.
MIRRORS = ((False, False), (True, False), (False, True), (True, True))
#: The input and its rotation by 180 degrees: the pair whose errors cancel best per step spent.
ROTATION = ((False, False), (True, True))
#: The copy sets by their size (``--mirror N``).
MIRROR_SETS = {4: MIRRORS, 2: ROTATION}


def _mirror(array: np.ndarray, lr: bool, ud: bool) -> np.ndarray:
    if lr:
        array = array[..., ::-1]
    if ud:
        array = array[..., ::-1, :]
    return np.ascontiguousarray(array)


class MirrorPolicy:
    """The mean of a recurrent policy's flows on the mirrored copies ``mirrors`` of each input,
    each mirrored back. The wrapped policy (a :class:`agents.policy.RecurrentPolicy`) runs once per
    copy, with a state per copy."""

    def __init__(self, policy, mirrors=MIRRORS) -> None:
        self.policy = policy
        self.mirrors = tuple((bool(lr), bool(ud)) for lr, ud in mirrors)
        if not self.mirrors:
            raise ValueError("MirrorPolicy needs at least one mirror")
        self.input_key = policy.input_key
        self.voxel_bins = getattr(policy, "voxel_bins", 5)
        self.device = getattr(policy, "device", "cpu")
        self._states: list = [None] * len(self.mirrors)

    def reset(self, mask=None) -> None:
        if mask is not None:
            raise ValueError("MirrorPolicy runs one sequence at a time: reset() without a mask")
        self._states = [None] * len(self.mirrors)

    def act(self, obs, window: Window | None = None) -> np.ndarray:
        """The mean flow of the mirrored copies (``agents.policy.FlowPolicy``); the window is not
        read (the wrapped network sees the mirrored observations only)."""
        part = np.asarray(obs[self.input_key] if isinstance(obs, dict) else obs)
        if part.ndim != 3:
            raise ValueError(f"MirrorPolicy acts on one window (C, H, W), got {part.shape}")
        total = None
        for k, (lr, ud) in enumerate(self.mirrors):
            self.policy.state = self._states[k]
            flow = _mirror(self.policy.act(_mirror(part, lr, ud)), lr, ud)
            self._states[k] = self.policy.state
            flow[0] *= -1 if lr else 1
            flow[1] *= -1 if ud else 1
            total = flow if total is None else total + flow
        return (total / len(self.mirrors)).astype(np.float32)
