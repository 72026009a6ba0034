"""agents.mirror: a policy's flow averaged over mirrored inputs, each mirror with its own state."""

import copy

import numpy as np
import pytest
import torch

from agents.mirror import MirrorPolicy
from agents.policy import RecurrentPolicy
from agents.registry import make_model


class _Gradient:
    """A 'network' that commutes with mirroring: its flow is the input's spatial gradient (x, y)."""

    input_key, voxel_bins, device = "count_image", 5, "cpu"
    state = None

    def act(self, obs):
        image = np.asarray(obs[self.input_key] if isinstance(obs, dict) else obs, np.float64)[0]
        gy, gx = np.gradient(image)
        return np.stack([gx, gy]).astype(np.float32)


class _Fixed(_Gradient):
    """A 'network' that ignores its input: always the same flow."""

    def __init__(self, flow):
        self.flow = flow

    def act(self, obs):
        return self.flow.copy()


def test_a_mirror_equivariant_flow_is_unchanged(rng):
    image = rng.random((2, 9, 13)).astype(np.float32)
    plain = _Gradient().act({"count_image": image})
    assert np.allclose(MirrorPolicy(_Gradient()).act({"count_image": image}), plain, atol=1e-6)


def test_each_mirror_is_mirrored_back_with_its_sign(rng):
    flow = rng.normal(size=(2, 5, 7)).astype(np.float32)
    expected = (flow
                + np.stack([-flow[0][:, ::-1], flow[1][:, ::-1]])
                + np.stack([flow[0][::-1], -flow[1][::-1]])
                + np.stack([-flow[0][::-1, ::-1], -flow[1][::-1, ::-1]])) / 4
    got = MirrorPolicy(_Fixed(flow)).act({"count_image": np.zeros((2, 5, 7), np.float32)})
    assert np.allclose(got, expected, atol=1e-6)
    with pytest.raises(ValueError, match="one window"):
        MirrorPolicy(_Fixed(flow)).act({"count_image": np.zeros((1, 2, 5, 7), np.float32)})


def test_each_mirror_carries_its_own_recurrent_state(rng):
    torch.manual_seed(0)
    net = RecurrentPolicy(make_model("ev-mgrflownet", width="cpu").eval())
    copies = [copy.deepcopy(net) for _ in range(4)]
    mirrored = MirrorPolicy(copy.deepcopy(net))
    inputs = [rng.poisson(0.3, (2, 32, 48)).astype(np.float32) for _ in range(3)]
    for x in inputs:
        by_hand = []
        for policy, (lr, ud) in zip(copies, [(False, False), (True, False), (False, True), (True, True)]):
            view = x[:, ::-1] if ud else x
            view = view[:, :, ::-1] if lr else view
            flow = policy.act(np.ascontiguousarray(view))
            flow = flow[:, ::-1] if ud else flow
            flow = flow[:, :, ::-1] if lr else flow
            by_hand.append(flow * np.array([-1 if lr else 1, -1 if ud else 1], np.float32)[:, None, None])
        assert np.allclose(mirrored.act({"count_image": x}), np.mean(by_hand, axis=0), atol=1e-5)
    single = MirrorPolicy(copy.deepcopy(net), mirrors=[(False, False)])
    net.reset()
    for x in inputs:  # one mirror, no flip: the policy itself, window after window
        assert np.array_equal(single.act({"count_image": x}), net.act(x))
