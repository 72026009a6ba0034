"""The benchmark's onnxruntime step (evflow_cli/commands/bench_onnx.py) against torch's: the same
flow from the exported graph (runs where onnxruntime is installed: ``pip install onnxruntime``)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from agents.registry import make_model
from evflow_cli.commands.bench_onnx import NetworkStep


def test_the_onnx_step_gives_torchs_flow_and_leaves_the_model_as_it_was():
    pytest.importorskip("onnxruntime")
    pytest.importorskip("onnx")
    torch.manual_seed(0)
    model = make_model("ev-mgrflownet", base_width=4)
    with torch.no_grad():  # a flow of a few pixels, so that the prior's alignment matters
        model.flow_scaling = 40.0
    step = NetworkStep(model, (37, 50))
    before = step.run_torch()
    run = step.onnxruntime_runner(threads=1)
    flow = run()
    assert flow.shape == before.shape == (2, 37, 50) and np.abs(before).max() > 0.1
    np.testing.assert_allclose(flow, before, atol=2e-4 * np.abs(before).max())
    np.testing.assert_array_equal(step.run_torch(), before)  # the torch path is untouched by the export
    assert step.parity() < 2e-4 * np.abs(before).max()
