"""The shipped default's flow on fixed windows, against the values it gave when they were stored
(tests/default_flow_reference.json, 2026-12-06): a refactoring that changes what the default
computes, alone or in its mode (the proposal finished by a short solve), fails here. The values
are remade by ``python -c "from tests.test_default_flow import remake; remake()"`` only when the
default itself changes on purpose."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

REFERENCE = Path(__file__).parent / "default_flow_reference.json"


def default_flows() -> dict[str, list[np.ndarray]]:
    """The default's flow on the first three 1-frame windows of synthetic-mini's first recording,
    the network alone and in the default's mode."""
    from agents.policy import RecurrentPolicy
    from agents.pretrained import default_finish
    from agents.rollout import rollout
    from agents.wrappers.refine import FinishedPolicy
    from envs.env import EventFlowEnv

    flows = {}
    for mode in ("network", "finished"):
        policy = RecurrentPolicy.from_pretrained()
        if mode == "finished":
            policy = FinishedPolicy(policy, default_finish())
        env = EventFlowEnv("synthetic-mini", compute_reward=False, sequences=[0], observations=(policy.input_key,),
                           voxel_bins=policy.voxel_bins)
        flows[mode] = [step.flow for step in rollout(policy, env, options={"sequence": 0}, max_windows=3)]
        env.close()
    return flows


def _summary(flows):
    return [{"sum": float(f.sum()), "abs_sum": float(np.abs(f).sum()), "pixels": f[:, ::16, ::16].round(6).tolist()}
            for f in flows]


def remake() -> None:
    REFERENCE.write_text(json.dumps({mode: _summary(f) for mode, f in default_flows().items()}, indent=1) + "\n")


@pytest.mark.parametrize("mode", ["network", "finished"])
def test_the_defaults_flow_is_what_it_was(mode):
    stored = json.loads(REFERENCE.read_text())[mode]
    now = _summary(default_flows()[mode])
    # the finish's compiled kernels add in parallel, in no fixed order: a run differs by ~1e-5 px
    atol = 1e-5 if mode == "network" else 1e-3
    assert len(now) == len(stored) == 3
    for got, want in zip(now, stored):
        assert got["abs_sum"] > 0
        np.testing.assert_allclose(got["pixels"], want["pixels"], rtol=1e-4, atol=atol)
        assert got["abs_sum"] == pytest.approx(want["abs_sum"], rel=1e-4 if mode == "network" else 1e-3)
