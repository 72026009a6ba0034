"""agents/dormant.py and ``--revive``: dormant decoder channels get fresh incoming weights and zero
outgoing ones, so the flow is exactly unchanged, the channels fire again, and their outgoing
weights receive a gradient; a training run started with ``--revive`` takes its first step on the
same loss as without it."""

import json

import numpy as np
import pytest
import torch

from agents.checkpoint import load_checkpoint, save_checkpoint
from agents.dormant import FiringRecord, revive_decoder
from agents.registry import make_model

KILLED = [1, 3, 6]


def network(name: str = "ev-mgrflownet"):
    torch.manual_seed(0)
    return make_model(name, base_width=4, in_channels=5, flow_scaling=32.0).eval()


def kill(model, level: int = 0, channels=KILLED) -> None:
    with torch.no_grad():
        model.decoder.upsamples[level].conv.bias[channels] = -1e6


def fired(model, x) -> dict:
    record = FiringRecord(model)
    try:
        with torch.no_grad():
            model(x, None)
    finally:
        record.close()
    return record.fired


@pytest.mark.parametrize("name", ["ev-mgrflownet", "ev-flownet", "convgru-ev-flownet"])
def test_revival_keeps_the_flow_and_the_channels_fire_again(name):
    model = network(name)
    kill(model, 0)
    kill(model, 2, [0])
    x = torch.rand(2, 5, 32, 32)
    before = fired(model, x)
    assert set(torch.nonzero(~before["decoder.upsamples.0"]).flatten().tolist()) >= set(KILLED)
    with torch.no_grad():
        flows_before, _ = model(x, None)
    untouched = {k: v.clone() for k, v in model.state_dict().items() if k.startswith(("downs.", "residual."))}
    stage2 = model.decoder.upsamples[2].conv.weight[0].clone()

    revived = revive_decoder(model, before, seed=0)

    assert revived["decoder.upsamples.0"] == int((~before["decoder.upsamples.0"]).sum())
    assert revived["decoder.upsamples.2"] >= 1
    with torch.no_grad():
        flows_after, _ = model(x, None)
    for a, b in zip(flows_before, flows_after):
        assert torch.equal(a, b)  # zero outgoing weights: bitwise the same flow
    after = fired(model, x)
    assert after["decoder.upsamples.0"][KILLED].any()  # (a fresh channel may still be silent by chance)
    stage = model.decoder.upsamples[0]
    torch.manual_seed(0)  # the first fresh layer drawn: stage 0's, as its own class draws it
    reference = type(stage)(stage.conv.in_channels, stage.conv.out_channels).conv
    assert torch.equal(stage.conv.weight[KILLED], reference.weight[KILLED])
    assert torch.equal(stage.conv.bias[KILLED], reference.bias[KILLED])
    assert not torch.equal(model.decoder.upsamples[2].conv.weight[0], stage2)
    heads, stages = model.decoder.heads, model.decoder.upsamples
    assert (heads[0].weight[:, KILLED] == 0).all() and (stages[1].conv.weight[:, KILLED] == 0).all()
    assert all(torch.equal(model.state_dict()[k], v) for k, v in untouched.items())


def test_revived_channels_receive_a_gradient_where_dead_ones_did_not():
    model = network().train()
    kill(model, 0)
    x = torch.rand(2, 5, 32, 32)

    def head_gradient():
        model.zero_grad()
        flows, _ = model(x, None)
        sum(f.square().sum() for f in flows).backward()
        return model.decoder.heads[0].weight.grad[:, KILLED].abs().sum()

    assert head_gradient() == 0  # dead inputs: no gradient to their outgoing weights
    revive_decoder(model, fired(model, x), seed=0)
    assert head_gradient() > 0


def test_the_fresh_weights_follow_the_seed_and_spare_live_channels():
    a, b, c = network(), network(), network()
    x = torch.rand(1, 5, 32, 32)
    for model in (a, b, c):
        kill(model)
    live = a.decoder.upsamples[0].conv.weight[0].clone()
    revive_decoder(a, fired(a, x), seed=5)
    revive_decoder(b, fired(b, x), seed=5)
    revive_decoder(c, fired(c, x), seed=6)
    wa, wb, wc = (m.decoder.upsamples[0].conv.weight for m in (a, b, c))
    assert torch.equal(wa, wb) and not torch.equal(wa[KILLED], wc[KILLED])
    assert torch.equal(wa[0], live)


def test_the_global_generator_is_left_as_it_was():
    model = network()
    kill(model)
    x = torch.rand(1, 5, 32, 32)
    mask = fired(model, x)
    torch.manual_seed(7)
    expected = torch.rand(3)
    torch.manual_seed(7)
    revive_decoder(model, mask, seed=0)
    assert torch.equal(torch.rand(3), expected)


def test_a_network_without_a_flow_decoder_is_refused():
    model = network("xlif-ev-flownet")
    with pytest.raises(ValueError, match="XLIFEVFlowNet: reviving dormant channels needs a FlowDecoder"):
        revive_decoder(model, {}, seed=0)


def test_train_revive_starts_on_the_same_loss_and_needs_init(tmp_path, capsys):
    from evflow_cli.commands import train as train_script
    from tests.recordings import write_translating_recording

    data = write_translating_recording(tmp_path / "dots.h5", np.random.default_rng(3), sensor_size=(32, 32))
    common = ["--device", "cpu", "--data", str(data), "--model", "ev-mgrflownet", "--width", "4",
              "--num-envs", "2", "--unroll", "3", "--val-data", "", "--no-progress", "--lr", "1e-3"]
    train_script.main([*common, "--steps", "2", "--out", str(tmp_path / "first")])
    payload = load_checkpoint(tmp_path / "first" / "checkpoint.pt")
    payload["model"]["decoder.upsamples.0.conv.bias"][KILLED] = -1e6
    save_checkpoint(tmp_path / "killed.pt", payload)

    runs = {}
    for name, extra in (("plain", []), ("revived", ["--revive", "2"])):
        capsys.readouterr()
        train_script.main([*common, "--steps", "2", "--init", str(tmp_path / "killed.pt"), *extra,
                           "--out", str(tmp_path / name)])
        runs[name] = ([json.loads(line) for line in (tmp_path / name / "metrics.jsonl").read_text().splitlines()],
                      capsys.readouterr().out)
    (plain, _), (revived, said) = runs["plain"], runs["revived"]
    assert revived[0]["loss"] == pytest.approx(plain[0]["loss"], rel=1e-6)  # the same flow at the first step
    assert revived[1]["loss"] != plain[1]["loss"]  # but other weights after it
    assert "--revive: dormant decoder channels re-initialised: decoder.upsamples.0" in said
    with pytest.raises(SystemExit):
        train_script.parse_args(["--revive", "2"])
    assert "--revive re-initialises the dormant channels of the --init weights" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        train_script.parse_args(["--revive", "2", "--init", "w.pt", "--resume"])
    assert "not --resume (a resumed run keeps its weights)" in capsys.readouterr().err
