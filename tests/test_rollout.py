"""agents.rollout and the policy interface (agents.policy.FlowPolicy): the one loop every consumer
rolls, against a hand-written env loop; plug-ins with ``act(obs)`` alone adapted."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from agents.policy import FlowPolicy, ObservationOnlyPolicy, RecurrentPolicy, ZeroFlowPolicy, as_flow_policy
from agents.registry import make_model
from agents.rollout import observation_options, rollout
from envs.env import EventFlowEnv, NoWindowsError
from envs.windows import window_bounds
from losses import window_loss
from tests.recordings import write_translating_recording


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    return str(write_translating_recording(tmp_path_factory.mktemp("rollout") / "dots.h5", np.random.default_rng(3),
                                           sensor_size=(24, 32)))


def _network():
    torch.manual_seed(0)
    return RecurrentPolicy(make_model("unet-feedforward", base_width=4).eval())


class _Spy:
    """A window-aware policy that records what it was given."""

    def __init__(self):
        self.resets, self.windows = 0, []

    def reset(self, mask=None):
        self.resets += 1

    def act(self, obs, window=None):
        self.windows.append(window)
        return np.full((2, *obs["count_image"].shape[-2:]), 0.5, np.float32)


def test_rollout_steps_every_window_in_order_with_the_policys_flow_and_reward(recording):
    env = EventFlowEnv(recording, window="time", window_size=20_000)
    spy = _Spy()
    steps = list(rollout(spy, env, options={"sequence": 0}))
    bounds = window_bounds(env.sources[0].reader(), "time", 20_000)
    assert spy.resets == 1 and [s.index for s in steps] == list(range(len(bounds)))
    assert [(s.window.t_start, s.window.t_end) for s in steps] == [tuple(b) for b in bounds[:, :2].tolist()]
    assert all(s.window is w and s.info["window"] is w for s, w in zip(steps, spy.windows))
    for s in steps:  # the reward is the env's for that window's flow
        expected = -float(window_loss(torch.from_numpy(s.flow)[None], s.window, env.loss_weights,
                                      flow_scaling=env.flow_scaling).loss)
        assert s.reward == pytest.approx(expected, rel=1e-5) and s.seconds >= 0
    assert list(rollout(_Spy(), env, options={"sequence": 0}, max_windows=2))[-1].index == 1
    env.close()


def test_rollout_of_a_network_is_the_hand_written_env_loop(recording):
    """The state carried from window to window and fresh at the start, as in a loop by hand."""
    env = EventFlowEnv(recording, window="frames", compute_reward=False)
    by_hand, policy = [], _network()
    obs, info = env.reset(options={"sequence": 0})
    policy.reset()
    truncated = False
    while not truncated:
        flow = policy.act(obs)
        by_hand.append(flow)
        obs, _, _, truncated, info = env.step(flow)
    for _ in range(2):  # twice: the second rollout starts fresh too
        flows = [s.flow for s in rollout(policy, env, options={"sequence": 0})]
        assert len(flows) == len(by_hand) and all(np.array_equal(a, b) for a, b in zip(flows, by_hand))
    env.close()


def test_a_recording_without_windows_raises_at_the_call(recording):
    env = EventFlowEnv(recording, window="time", window_size=20_000)
    spy = _Spy()
    with pytest.raises(NoWindowsError):
        rollout(spy, env, options={"sequence": 0, "start": 10**12})  # after the recording's end
    assert spy.resets == 0
    env.close()


class _ObservationOnly:
    """A plug-in written against act(obs) alone, with a reset that takes no mask."""

    input_key, voxel_bins = "count_image", 5

    def __init__(self):
        self.calls = 0

    def reset(self):
        self.calls = 0

    def act(self, obs):
        self.calls += 1
        return np.zeros((2, *obs["count_image"].shape[-2:]), np.float32)


def test_plugins_with_act_obs_are_adapted_and_the_others_pass_through(recording):
    plugin = _ObservationOnly()
    adapted = as_flow_policy(plugin)
    assert isinstance(adapted, ObservationOnlyPolicy) and isinstance(adapted, FlowPolicy)
    assert adapted.input_key == "count_image" and adapted.policy is plugin
    adapted.reset()
    obs = {"count_image": np.zeros((2, 4, 5), np.float32)}
    assert adapted.act(obs, window={"t": []}).shape == (2, 4, 5) and plugin.calls == 1
    for policy in (_network(), _Spy(), ZeroFlowPolicy()):
        assert as_flow_policy(policy) is policy
    env = EventFlowEnv(recording, window="time", window_size=20_000, compute_reward=False)
    assert len(list(rollout(plugin, env, options={"sequence": 0}, max_windows=3))) == 3 and plugin.calls == 3
    env.close()


def test_zero_flow_and_the_observations_a_policy_needs():
    obs = {"count_image": np.ones((2, 6, 7), np.float32)}
    assert np.array_equal(ZeroFlowPolicy().act(obs), np.zeros((2, 6, 7), np.float32))
    assert observation_options(ZeroFlowPolicy()) == {"observations": ("count_image",), "voxel_bins": 5}
    voxel = RecurrentPolicy(make_model("unet-feedforward", in_channels=3, base_width=4), input_key="voxel_grid",
                            voxel_bins=3)
    assert observation_options(voxel) == {"observations": ("count_image", "voxel_grid"), "voxel_bins": 3}
