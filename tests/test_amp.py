"""Mixed precision (``--amp``): what each choice means on which device, the policy's autocast
(float32 out, float32 state), and the option through training, checkpoint and resume."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from agents.checkpoint import load_checkpoint
from agents.policy import autocast_dtype
from evflow_cli.commands import train as train_script
from tests.device_parity import network_run, relative_error
from tests.recordings import write_translating_recording


def test_amp_choices_per_device():
    assert autocast_dtype("auto", "cpu") is None and autocast_dtype("off", "cpu") is None
    assert autocast_dtype("bf16", "cpu") == torch.bfloat16
    with pytest.raises(ValueError, match="amp fp16 needs a CUDA device"):
        autocast_dtype("fp16", "cpu")
    with pytest.raises(ValueError, match=r"amp must be one of .*got 'half'"):
        autocast_dtype("half", "cpu")


def test_bf16_policy_returns_float32_flows_and_state_near_float32():
    from agents import RecurrentPolicy, make_model
    from tests.device_parity import count_images

    policy = RecurrentPolicy(make_model("ev-mgrflownet", base_width=4, flow_scaling=16.0), autocast=torch.bfloat16)
    flows = policy(count_images(2, 24, 40, seed=0))
    assert all(flow.dtype == torch.float32 for flow in flows)
    assert all(value.dtype == torch.float32 for value in policy.state.values())
    fp32, bf16 = network_run("ev-mgrflownet", "cpu"), network_run("ev-mgrflownet", "cpu", autocast=torch.bfloat16)
    assert relative_error(bf16["flows"], fp32["flows"]) < 0.05 and relative_error(bf16["grads"], fp32["grads"]) < 0.1


def test_amp_is_stored_kept_on_resume_and_may_change_like_the_device(tmp_path):
    recording = write_translating_recording(tmp_path / "dots.h5", np.random.default_rng(3), sensor_size=(32, 32))
    run = tmp_path / "run"
    common = ["--val-data", "", "--no-progress", "--device", "cpu", "--out", str(run)]
    train_script.main(["--data", str(recording), "--width", "4", "--num-envs", "1", "--unroll", "2", "--steps", "1",
                       "--amp", "bf16", *common])
    assert load_checkpoint(run / "checkpoint.pt")["config"]["amp"] == "bf16"
    train_script.main(["--resume", "--steps", "2", *common])  # no --amp: the stored one
    assert load_checkpoint(run / "checkpoint.pt")["config"]["amp"] == "bf16"
    train_script.main(["--resume", "--steps", "3", "--amp", "off", *common])  # a run option: no --allow-changes
    payload = load_checkpoint(run / "checkpoint.pt")
    assert payload["config"]["amp"] == "off" and payload["step"] == 3
    with pytest.raises(SystemExit):
        train_script.main(["--resume", "--steps", "4", "--amp", "half", *common])
