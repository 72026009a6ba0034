"""agents.wrappers.mirror: a policy's flow averaged over mirrored inputs, each mirror with its own state."""

import copy

import numpy as np
import pytest
import torch

from agents.policy import RecurrentPolicy
from agents.registry import make_model
from agents.wrappers.mirror import ROTATION, MirrorPolicy
from evflow_cli.commands import evaluate as evaluate_script
from tests.recordings import write_translating_recording


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


def test_the_rotation_pair_averages_the_flow_with_its_half_turn(rng):
    flow = rng.normal(size=(2, 5, 7)).astype(np.float32)
    turned = -np.rot90(flow, 2, axes=(1, 2))  # a half turn reverses both components
    got = MirrorPolicy(_Fixed(flow), ROTATION).act({"count_image": np.zeros((2, 5, 7), np.float32)})
    assert np.allclose(got, (flow + turned) / 2, atol=1e-6)


def test_evaluate_mirror_rows_by_number_of_copies(tmp_path, rng):
    path = write_translating_recording(tmp_path / "rec.h5", rng, sensor_size=(32, 48))
    out = tmp_path / "ev"
    evaluate_script.main(["--model", "unet-feedforward", "--width", "4", "--mirror", "2", "--dt", "1",
                          "--data", str(path), "--out", str(out), "--no-progress", "--pictures", "0",
                          "--max-windows", "2"])
    table = (out / "table.md").read_text()
    assert "| unet-feedforward + mirror 2 |" in table and "+ mirror |" not in table
    evaluate_script.main(["--model", "unet-feedforward", "--width", "4", "--mirror", "--dt", "1",
                          "--data", str(path), "--out", str(out), "--no-progress", "--pictures", "0",
                          "--max-windows", "2", "--overwrite"])  # the same --out again: replaced when asked
    assert "| unet-feedforward + mirror |" in (out / "table.md").read_text()
    with pytest.raises(SystemExit, match="--mirror"):
        evaluate_script.main(["--zero", "--mirror", "3", "--data", str(path), "--out", str(out)])
