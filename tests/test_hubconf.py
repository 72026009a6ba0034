"""hubconf.py: torch.hub.load(<checkout>, ..., source="local") returns the shipped models, whose
flow on a window is that of agents.pretrained.load_pretrained, and the baselines untrained."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from agents.policy import RecurrentPolicy
from agents.pretrained import DEFAULT_PRETRAINED, load_pretrained
from envs.env import EventFlowEnv
from tests.recordings import write_translating_recording

CHECKOUT = str(Path(__file__).resolve().parents[1])


def flow_on_a_window(model: torch.nn.Module, info: dict, recording: Path) -> np.ndarray:
    """The model's flow on the recording's second window, its state carried from the first."""
    env = EventFlowEnv(str(recording), observations=(info["input"],), voxel_bins=info["voxel_bins"],
                       compute_reward=False)
    policy = RecurrentPolicy(model, input_key=info["input"], voxel_bins=info["voxel_bins"])
    obs, _ = env.reset(options={"sequence": 0})
    obs, *_ = env.step(policy.act(obs))
    flow = policy.act(obs)
    env.close()
    return flow


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    path = tmp_path_factory.mktemp("data") / "dots.h5"
    return write_translating_recording(path, np.random.default_rng(5), sensor_size=(32, 48))


@pytest.mark.parametrize("name", [None, "ev-mgrflownet-cpu-synthetic"])
def test_hub_load_gives_the_flow_of_load_pretrained(recording, name):
    kwargs = {} if name is None else {"name": name}
    model = torch.hub.load(CHECKOUT, "ev_mgrflownet", source="local", pretrained=True, **kwargs)
    reference, info = load_pretrained(name)
    assert model.provenance["name"] == (name or DEFAULT_PRETRAINED) and not model.training
    flow = flow_on_a_window(model, model.provenance, recording)
    assert np.abs(flow).max() > 0
    np.testing.assert_array_equal(flow, flow_on_a_window(reference, info, recording))


def test_hub_builds_the_untrained_baselines_and_model():
    untrained = torch.hub.load(CHECKOUT, "convgru_ev_flownet", source="local", width=4)
    flows, _ = untrained(torch.zeros(1, 2, 32, 32), None)
    assert flows[-1].shape == (1, 2, 32, 32)
    assert torch.hub.load(CHECKOUT, "ev_flownet", source="local", width=4).config["in_channels"] == 4
    with pytest.raises(ValueError, match="no weights are shipped for xlif-ev-flownet"):
        torch.hub.load(CHECKOUT, "xlif_ev_flownet", source="local", pretrained=True)
    untrained = torch.hub.load(CHECKOUT, "ev_mgrflownet", source="local", pretrained=False, width=4)
    assert untrained.config["base_width"] == 4


def test_hub_flow_takes_events_and_builds_its_own_input():
    from agents import predict_flow
    from tests.recordings import translating_dots

    events, _ = translating_dots(np.random.default_rng(6), sensor_size=(32, 48), duration_us=100_000)
    array = np.zeros(len(events), dtype=[("x", "<i2"), ("y", "<i2"), ("t", "<i8"), ("p", "?")])
    array["x"], array["y"], array["t"], array["p"] = events.x, events.y, events.t, events.p > 0
    flows, bounds = torch.hub.load(CHECKOUT, "flow", array, (48, 32, 2), source="local", max_windows=2)
    assert flows.shape == (2, 2, 32, 48) and bounds.shape == (2, 2)
    reference, _ = predict_flow(array, (32, 48), max_windows=2)
    np.testing.assert_array_equal(flows, reference)
