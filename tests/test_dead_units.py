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


def test_watch_retrains_the_stored_configuration_and_reports_each_stretch(du, tmp_path):
    """The watched run is the stored run again (the same losses over its first steps), its lines
    come every `every` steps, and a layer the network lacks is named."""
    import json

    import numpy as np

    from evflow_cli.commands import train as train_script
    from tests.recordings import write_translating_recording

    data = write_translating_recording(tmp_path / "dots.h5", np.random.default_rng(3), sensor_size=(32, 32))
    out = tmp_path / "run"
    train_script.main(["--device", "cpu", "--data", str(data), "--model", "convgru-ev-flownet", "--width", "4",
                       "--num-envs", "2", "--unroll", "3", "--val-data", "", "--no-progress", "--lr", "1e-3",
                       "--steps", "4", "--out", str(out)])
    logged = [json.loads(line) for line in (out / "metrics.jsonl").read_text().splitlines()]
    lines = du.watch(out / "checkpoint.pt", steps=4, every=2, echo=lambda _: None)
    assert [line["step"] for line in lines] == [2, 4]
    for line, pair in zip(lines, (logged[:2], logged[2:4])):
        expected = sum(r["loss"] for r in pair) / sum(r["zero_flow_loss"] for r in pair)
        assert line["loss_over_zero"] == pytest.approx(expected, rel=1e-5)
        assert {"downs.0", "decoder.upsamples.0"} <= set(line)
    with pytest.raises(ValueError, match="deep_memory_up not ReLU layers of convgru-ev-flownet"):
        du.watch(out / "checkpoint.pt", steps=1, layers=("deep_memory_up",), echo=lambda _: None)
