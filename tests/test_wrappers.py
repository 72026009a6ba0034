"""agents.wrappers: the coarse grid, the gain and the combinations (mirror, sub-windows and
refinement have their own test files: test_mirror, test_subwindows, test_evaluation)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from agents.policy import RecurrentPolicy
from agents.registry import make_model
from agents.wrappers import CoarsePolicy, CombinedPolicy, GainPolicy, RefinedPolicy, SubWindowPolicy
from envs.env import EventFlowEnv
from envs.windows import Window
from losses import EventBatch, window_loss
from tests.recordings import translating_dots, write_translating_recording


class _Constant:
    """A 'network' answering every input with the same flow vector, at the input's size."""

    input_key, voxel_bins, device = "count_image", 5, "cpu"

    def __init__(self, vector=(1.5, -0.5)):
        self.vector, self.inputs = np.asarray(vector, np.float32), []

    def reset(self, mask=None):
        pass

    def act(self, obs, window=None):
        self.inputs.append(np.asarray(obs[self.input_key]))
        return np.broadcast_to(self.vector[:, None, None], (2, *self.inputs[-1].shape[-2:])).copy()


def _window(rng, size=(21, 31), velocity=(120.0, -90.0)):
    events, (t0, t1) = translating_dots(rng, sensor_size=size, velocity=velocity, duration_us=33_333,
                                        num_dots=60, events_per_s=200_000)
    return Window.of(events, t0, t1)


def test_coarse_bins_the_events_and_scales_the_flow_back(rng):
    window = _window(rng)
    obs = {"count_image": np.zeros((2, 21, 31), np.float32)}
    inner = _Constant()
    flow = CoarsePolicy(inner, factor=2).act(obs, window)
    assert flow.shape == (2, 21, 31) and np.allclose(flow, 2 * inner.vector[:, None, None])  # coarse pixels x 2
    image = inner.inputs[-1]
    assert image.shape == (2, 11, 16) and image.sum() == pytest.approx(len(window.events) / 4)  # each count / F^2
    CoarsePolicy(inner, factor=2, splits=3).act(obs, window)
    assert len(inner.inputs) == 4  # one step per sub-window
    with pytest.raises(ValueError, match="window"):
        CoarsePolicy(inner, factor=2).act(obs)
    with pytest.raises(ValueError, match="factor"):
        CoarsePolicy(inner, factor=0)


def test_coarse_by_one_is_the_network_on_the_windows_own_events(tmp_path, rng):
    path = write_translating_recording(tmp_path / "dots.h5", rng, sensor_size=(24, 32))
    env = EventFlowEnv(str(path), compute_reward=False)
    obs, info = env.reset(options={"sequence": 0})
    torch.manual_seed(0)
    plain = RecurrentPolicy(make_model("unet-feedforward", base_width=4).eval())
    coarse = CoarsePolicy(RecurrentPolicy(make_model("unet-feedforward", base_width=4).eval()), factor=1)
    coarse.policy.model.load_state_dict(plain.model.state_dict())
    np.testing.assert_allclose(coarse.act(obs, info["window"]), plain.act(obs), atol=1e-5)
    env.close()


def test_gain_multiplies_the_flow_and_passes_the_window_on(rng):
    window = _window(rng)
    obs = {"count_image": np.zeros((2, 21, 31), np.float32)}
    assert np.allclose(GainPolicy(_Constant(), 2.0).act(obs), 2 * np.array([1.5, -0.5])[:, None, None])
    inner = SubWindowPolicy(_Constant(), splits=2)
    GainPolicy(inner, 0.5).act(obs, window)  # a window-aware policy inside gets the window
    assert len(inner.policy.inputs) == 2


def test_combinations_average_or_pick_the_flow_the_events_prefer(rng):
    window = _window(rng)
    obs = {"count_image": np.zeros((2, 21, 31), np.float32)}
    truth = np.array([120.0, -90.0]) * 33_333 / 1e6
    right, wrong = _Constant(truth), _Constant(-truth)
    average = CombinedPolicy([right, None], "avg").act(obs, window)
    assert np.allclose(average, truth[:, None, None] / 2)
    pick = CombinedPolicy([wrong, None, right], "pick")
    chosen = pick.act(obs, window)
    losses = [float(window_loss(torch.from_numpy(f)[None], EventBatch.from_windows([window]), flow_scaling=31.0).loss)
              for f in (wrong.act(obs), np.zeros_like(chosen), right.act(obs))]
    assert np.argmin(losses) == 2 and np.allclose(chosen, truth[:, None, None]) and pick.picked == [0, 0, 1]
    with pytest.raises(ValueError, match="how"):
        CombinedPolicy([right], "max")
    with pytest.raises(ValueError, match="window"):
        pick.act(obs)


def test_window_aware_wrappers_refuse_to_act_without_the_window():
    obs = {"count_image": np.zeros((2, 5, 6), np.float32)}
    for policy in (SubWindowPolicy(_Constant(), 2), RefinedPolicy(_Constant(), steps=1)):
        with pytest.raises(ValueError, match="act\\(obs, window\\)"):
            policy.act(obs)
    assert SubWindowPolicy(_Constant(), 1).act(obs).shape == (2, 5, 6)  # one sub-window: the policy's own flow
