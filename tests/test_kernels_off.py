"""The path CUDA takes, run on the CPU: with the compiled CPU kernels switched off
(``losses.cpu_kernels(False)``, ``EVFLOW_CPU_KERNELS=0``) every network keeps NCHW activations
and every loss its torch expressions, which is what a GPU runs. Here they are held to the kernels'
results: networks forward and backward, the losses and their gradients, two training steps."""

from __future__ import annotations

import os
import subprocess
import sys

import numpy as np
import pytest
import torch

from agents import make_model
from losses import cpu_kernels, cpu_kernels_enabled
from losses.kernel_switch import ENV_VAR, use_cpu_kernels
from tests.device_parity import MODEL_NAMES, count_images, loss_run, network_run, relative_error, training_run
from tests.recordings import write_translating_recording


def test_the_switch_routes_cpu_tensors_and_restores_itself():
    x = torch.zeros(3)
    model = make_model("ev-mgrflownet", base_width=4, flow_scaling=16.0)
    before = cpu_kernels_enabled()
    with cpu_kernels(True):
        assert use_cpu_kernels(x) and not use_cpu_kernels(x.half())
        assert model._use_channels_last(count_images(1, 16, 16, 0)) is True
        with cpu_kernels(False):
            assert not cpu_kernels_enabled() and not use_cpu_kernels(x)
            assert model._use_channels_last(count_images(1, 16, 16, 0)) is False  # NCHW, as on CUDA
        assert cpu_kernels_enabled()
    assert cpu_kernels_enabled() == before


def test_the_environment_variable_switches_kernels_off_and_a_bad_value_is_named():
    code = "from losses import cpu_kernels_enabled; print(cpu_kernels_enabled())"
    for value, expected in (("0", "False"), ("off", "False"), ("1", "True")):
        done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                              env={**os.environ, ENV_VAR: value})
        assert done.stdout.strip() == expected, done.stderr[-2000:]
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env={**os.environ, ENV_VAR: "maybe"})
    assert done.returncode != 0 and f"{ENV_VAR}='maybe'" in done.stderr


@pytest.mark.parametrize("name", MODEL_NAMES)
def test_networks_forward_and_backward_alike_with_kernels_off(name):
    """Two windows (state carried) and the backward through both: flows and every parameter's
    gradient agree to float32 rounding (the layouts sum the convolutions in different orders)."""
    on = network_run(name, "cpu")
    with cpu_kernels(False):
        off = network_run(name, "cpu")
    np.testing.assert_allclose(off["flows"].numpy(), on["flows"].numpy(), rtol=1e-4, atol=1e-5 * 16)
    assert relative_error(off["grads"], on["grads"]) < 1e-4


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_losses_and_gradients_alike_with_kernels_off(dtype):
    on = loss_run("cpu", dtype=dtype)
    with cpu_kernels(False):
        off = loss_run("cpu", dtype=dtype)
    # float32: the kernels' polynomial exp and float64 row sums against torch's (docs/method.md, numerics)
    rtol, grad_tol = (1e-9, 1e-9) if dtype == torch.float64 else (1e-4, 1e-3)
    for key in on:
        np.testing.assert_allclose(off[key][0].numpy(), on[key][0].numpy(), rtol=rtol, atol=rtol * 1e-3, err_msg=key)
        assert relative_error(off[key][1], on[key][1]) < grad_tol, key


def test_two_training_steps_alike_with_kernels_off(tmp_path):
    recording = write_translating_recording(tmp_path / "dots.h5", np.random.default_rng(3), sensor_size=(32, 32))
    on = training_run(recording, "cpu")
    with cpu_kernels(False):
        off = training_run(recording, "cpu")
    np.testing.assert_allclose(off["losses"], on["losses"], rtol=1e-4)
    assert relative_error(off["weights"], on["weights"]) < 1e-4  # Adam's steps normalise the gradients' rounding
