"""Bring-your-own-model: a user-style package outside agents/ (tests/plugin_example) goes
through exactly the code path of a built-in model: make_model from a dotted path, the policy
wrapper, an env rollout, truncated-BPTT training on the env's loss, a checkpoint round trip."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from agents import MODELS, ModelLoadError, ProtocolError, RecurrentPolicy, make_model, register_model
from envs.env import EventFlowEnv
from losses import EventBatch, hmc_loss
from tests.recordings import write_translating_recording

PLUGIN = "plugin_example.tiny_flow:build"


@pytest.fixture(autouse=True)
def plugin_on_path(monkeypatch):
    """What a user does with PYTHONPATH: make their package importable."""
    monkeypatch.syspath_prepend(str(Path(__file__).parent))


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    return write_translating_recording(tmp_path_factory.mktemp("plugin") / "dots.h5", np.random.default_rng(5))


def _window(info: dict) -> dict:
    return info["window"]


def train_and_evaluate(spec: str, recording, **model_kwargs) -> tuple[torch.nn.Module, list[float]]:
    """What the training and evaluation scripts do with any model spec, in miniature: build it,
    wrap it, unroll windows with truncated BPTT on the HMC loss, then roll out the env."""
    torch.manual_seed(0)
    model = make_model(spec, in_channels=2, base_width=8, flow_scaling=64.0, **model_kwargs)
    policy = RecurrentPolicy(model)
    optimizer = torch.optim.Adam(policy.parameters(), lr=1e-4)
    env = EventFlowEnv(recording, window="time", window_size=20_000)

    obs, info = env.reset(seed=0)
    policy.reset()
    for _ in range(2):  # two truncated-BPTT chunks of 2 windows
        loss = 0.0
        for _ in range(2):
            flows = policy(torch.from_numpy(obs["count_image"])[None])
            loss = loss + hmc_loss(flows, EventBatch.from_windows([_window(info)])).loss
            obs, _, _, _, info = env.step(flows[-1][0].detach().numpy())
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        policy.detach()

    rewards = []
    obs, info = env.reset(seed=1)
    policy.reset()
    truncated = False
    while not truncated and len(rewards) < 4:
        obs, reward, _, truncated, info = env.step(policy.act(obs))
        rewards.append(reward)
    return model, rewards


@pytest.mark.parametrize("spec", [PLUGIN, "ev-mgrflownet"])
def test_same_code_path_trains_and_evaluates_plugin_and_built_in(spec, recording):
    model, rewards = train_and_evaluate(spec, recording)
    assert len(rewards) == 4 and all(np.isfinite(rewards))
    assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in model.parameters())


def test_plugin_checkpoint_round_trip():
    model = make_model(PLUGIN, in_channels=2, base_width=8, width="cpu", flow_scaling=32.0)
    # base_width and width are not in build()'s signature: dropped, and config says what was used.
    assert model.config == {"in_channels": 2, "flow_scaling": 32.0}
    checkpoint = {"model": PLUGIN, "config": model.config, "weights": model.state_dict()}
    rebuilt = make_model(checkpoint["model"], **checkpoint["config"])
    rebuilt.load_state_dict(checkpoint["weights"])
    x = torch.rand(1, 2, 10, 12)
    torch.testing.assert_close(rebuilt(x, None)[0][-1], model(x, None)[0][-1])


def test_plugin_honours_policy_state_semantics():
    policy = RecurrentPolicy(make_model(PLUGIN))
    x = torch.rand(2, 2, 9, 11)
    with torch.no_grad():
        first = policy(x)[-1]
        second = policy(x)[-1]
        policy.reset(mask=np.array([True, False]))
        third = policy(x)[-1]
    assert not torch.allclose(first, second)
    torch.testing.assert_close(third[0], first[0])
    policy.reset()
    assert policy.act({"count_image": x[0].numpy()}).shape == (2, 9, 11)


def test_register_model_by_name():
    from plugin_example.tiny_flow import build

    register_model("tiny-flow-test", build)
    try:
        model = make_model("tiny-flow-test", base_width=8)
        flows, state = model(torch.rand(1, 2, 8, 8), None)
        assert flows[-1].shape == (1, 2, 8, 8) and "memory" in state
        with pytest.raises(ValueError, match="already registered"):
            register_model("tiny-flow-test", lambda **kw: None)
    finally:
        MODELS.pop("tiny-flow-test", None)


@pytest.mark.parametrize(
    "spec, error, message",
    [
        ("no_such_package.flow:build", ModelLoadError, "cannot import module 'no_such_package.flow'"),
        ("plugin_example.tiny_flow:missing", ModelLoadError, "has no attribute 'missing'"),
        ("plugin_example.bad_models:not_callable", ModelLoadError, "is not callable"),
        ("plugin_example.tiny_flow", ModelLoadError, "unknown model"),
        ("plugin_example.bad_models:not_a_module", ProtocolError, "not a torch.nn.Module"),
        ("plugin_example.bad_models:wrong_flow_shape", ProtocolError, r"flows\[0\] must be"),
        ("plugin_example.bad_models:zero_state_is_not_fresh", ProtocolError, "all-zeros state"),
    ],
)
def test_bad_specs_fail_with_clear_errors(spec, error, message):
    with pytest.raises(error, match=message):
        make_model(spec)


class ObservationOnlyPolicy:
    """A user's policy written against ``act(obs)`` alone (no window), with a reset that takes no mask."""

    def __init__(self, policy: RecurrentPolicy) -> None:
        self.policy, self.flows = policy, []

    def reset(self) -> None:
        self.policy.reset()

    def act(self, obs):
        self.flows.append(self.policy.act(obs))
        return self.flows[-1]


def test_a_policy_plugin_with_act_obs_rolls_evaluates_and_wraps_as_the_network_does(recording):
    """The policy interface is act(obs, window=None); a plug-in's act(obs) is adapted wherever a
    policy is taken: the rollout, the evaluation, the wrappers."""
    from agents.evaluation import evaluate
    from agents.rollout import rollout
    from agents.wrappers import GainPolicy

    torch.manual_seed(0)
    network = RecurrentPolicy(make_model(PLUGIN, in_channels=2, flow_scaling=8.0))
    plugin = ObservationOnlyPolicy(network)
    env = EventFlowEnv(recording, window="time", window_size=20_000, compute_reward=False)
    flows = [step.flow for step in rollout(plugin, env, options={"sequence": 0}, max_windows=3)]
    direct = [step.flow for step in rollout(network, env, options={"sequence": 0}, max_windows=3)]
    env.close()
    assert all(np.array_equal(a, b) for a, b in zip(flows, direct)) and len(flows) == 3
    (mine,) = evaluate(plugin, recording, window="time", window_size=20_000, max_windows=3, progress=False)
    (theirs,) = evaluate(network, recording, window="time", window_size=20_000, max_windows=3, progress=False)
    assert mine.windows == 3 and mine.mean("hmc") == theirs.mean("hmc")
    (doubled,) = evaluate(GainPolicy(plugin, 2.0), recording, window="time", window_size=20_000, max_windows=3,
                          progress=False)
    assert doubled.windows == 3 and np.isfinite(doubled.mean("hmc"))
