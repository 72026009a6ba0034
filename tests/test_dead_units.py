"""tools/dead_units.py: channels forced never to fire (a large negative bias) are found dead, channels
forced always to fire are not, and every ReLU layer of EV-MGRFlowNet is watched."""

import pytest
import torch

from agents.policy import RecurrentPolicy
from agents.registry import make_model
from tests.conftest import load_script


@pytest.fixture(scope="module")
def du():
    return load_script("tools/dead_units.py")


def policy(name: str = "ev-mgrflownet") -> RecurrentPolicy:
    torch.manual_seed(0)
    model = make_model(name, base_width=4, in_channels=5, flow_scaling=32.0)
    return RecurrentPolicy(model, device="cpu", input_key="voxel_grid", voxel_bins=5)


def test_every_relu_layer_of_the_network_is_watched(du):
    names = [name for name, _ in du.relu_layers(policy().model)]
    assert {"downs.0", "downs.3", "residual.0", "residual.1", "deep_memory_up", "decoder.upsamples.0",
            "decoder.upsamples.3"} <= set(names)
    assert not any(name.startswith(("grus.", "decoder.heads", "decoder.refiners")) for name in names)


def test_forced_channels_are_found_dead_or_alive(du):
    p = policy()
    bias = p.model.decoder.upsamples[0].conv.bias
    with torch.no_grad():
        bias[[1, 3]] = -1e6  # never fires
        bias[0] = 1e6  # always fires
    out = du.dead_units(p, "synthetic-mini", dt=1, max_windows=2)
    first = out["decoder.upsamples.0"]
    assert first["channels"] == bias.numel()
    assert {1, 3} <= set(first["dead_channels"]) and 0 not in first["dead_channels"]
    assert first["dead"] == len(first["dead_channels"])
    assert 2 / bias.numel() <= first["zero_share"] < 1  # two whole channels zero, one never
    assert out["downs.0"]["zero_share"] < 1


def test_a_network_without_relu_layers_is_refused(du):
    class Plain(torch.nn.Module):
        def forward(self, x):
            return x

    class Fake:
        model = Plain()

    with pytest.raises(ValueError, match="no ReLU layer"):
        du.dead_units(Fake(), "synthetic-mini", max_windows=1)
