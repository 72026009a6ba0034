"""tools/state_use.py: a policy without memory scores the same either way (and as the evaluation
does); a policy that remembers loses exactly its memory when reset before every window."""

import math

import numpy as np
import pytest

from agents.evaluation import evaluate
from agents.policy import ZeroFlowPolicy
from tests.conftest import load_script

DATA, WINDOWS = "synthetic-mini", 4


@pytest.fixture(scope="module")
def su():
    return load_script("tools/state_use.py")


class ConstantFlow(ZeroFlowPolicy):
    """(3, -1) px on every window."""

    def act(self, obs, window=None):
        flow = super().act(obs, window)
        flow[0], flow[1] = 3.0, -1.0
        return flow


class RemembersAfterFirst(ConstantFlow):
    """Zero flow on the first window after a reset, ConstantFlow's afterwards."""

    def __init__(self):
        self.seen = 0

    def reset(self, mask=None):
        self.seen = 0

    def act(self, obs, window=None):
        self.seen += 1
        flow = super().act(obs, window)
        return flow if self.seen > 1 else flow * 0


def test_a_policy_without_memory_scores_alike_and_as_the_evaluation(su):
    carried = su.per_window_aee(ZeroFlowPolicy(), DATA, 1, WINDOWS)
    reset = su.per_window_aee(su.ResetEveryWindow(ZeroFlowPolicy()), DATA, 1, WINDOWS)
    assert carried == reset and carried
    plain = {r.name: r.mean("aee") for r in evaluate(None, DATA, window_size=1, max_windows=WINDOWS, progress=False)}
    for name, aees in carried.items():
        assert len(aees) == WINDOWS
        assert np.nanmean(aees) == pytest.approx(plain[name], rel=1e-9)


def test_reset_before_every_window_removes_the_memory_and_nothing_else(su):
    zero = su.per_window_aee(ZeroFlowPolicy(), DATA, 1, WINDOWS)
    constant = su.per_window_aee(ConstantFlow(), DATA, 1, WINDOWS)
    carried = su.per_window_aee(RemembersAfterFirst(), DATA, 1, WINDOWS)
    reset = su.per_window_aee(su.ResetEveryWindow(RemembersAfterFirst()), DATA, 1, WINDOWS)
    for name in zero:
        assert carried[name] == [zero[name][0], *constant[name][1:]]  # a fresh memory at each sequence's start
        assert reset[name] == zero[name]
        assert constant[name][1:] != zero[name][1:]  # the two policies do differ there


def test_places_average_their_own_windows(su):
    aees = [1.0, 2.0, 4.0, float("nan"), 6.0, *[10.0] * 10, 20.0, 30.0]
    out = su.by_place(aees)
    assert out == {"first": 1.0, "1-4": 4.0, "5-14": 10.0, "15+": 25.0}
    assert math.isnan(su.by_place([1.0])["1-4"])


def test_the_table_has_as_many_cells_in_every_row(su):
    carried = {"a": [1.0, 2.0], "b": [3.0]}
    text = su.table("t", carried, carried)
    rows = [line for line in text.splitlines() if line.startswith("|")]
    assert len({line.count("|") for line in rows}) == 1 and len(rows) == 5
    assert rows[-1].endswith("| 2.250 | 2.250 |")  # the mean over sequences of the sequences' means
