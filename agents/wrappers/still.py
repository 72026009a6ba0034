"""Still scenes stay still: a policy's flow kept only where the window's own events prefer it to
zero flow (``scripts/evaluate.py --still``, ``scripts/predict.py --still``)::

    policy = StillGuard(RefinedPolicy(RecurrentPolicy.from_pretrained(), steps=3))
    flow = policy.act(obs, window)   # zero flow where the events support no motion

A fixed camera over a street fires noise and hot pixels everywhere and real events only where
something moves. A network (or a solve) that puts flow on the noise sharpens nothing and raises
the window's loss above zero flow's: the env's reward says so, and the guard listens to it.
"""

from __future__ import annotations

from .combine import CombinedPolicy

__all__ = ["StillGuard"]


class StillGuard(CombinedPolicy):
    """The wrapped policy's flow where it lowers the window's loss below zero flow's, zero flow
    otherwise (a tie and a window without events included): ``CombinedPolicy([None, policy],
    "pick")``, so the guarded flow never scores a window worse than zero flow, whatever the policy
    does. The loss is the env's reward with the opposite sign (``losses.window_loss``: L_HMC,
    paper weights, border rule, flow scaling max(H, W)). The policy's recurrent state carries its
    own flow (a still window does not undo what it learned before). ``kept`` / ``windows``: the
    windows whose flow was kept / seen. Cost: two loss evaluations per window, no graph.
    """

    def __init__(self, policy) -> None:
        super().__init__([None, policy], "pick")
        self.policy = self.policies[1]

    @property
    def kept(self) -> int:
        return self.picked[1]

    @property
    def windows(self) -> int:
        return sum(self.picked)
