"""One step of a recurrent flow network exported to ONNX and run by onnxruntime, beside torch's
own step: the benchmark's measurement of an inference runtime made for CPUs (docs/performance.md,
"predict at 1280x720"). onnxruntime is not a dependency; without it only the torch step runs.

The exported graph is the network between its input and its finest flow: the padded input, the
prior flow already aligned (``losses.forward_warp_flow``, run by torch in both paths, since its
scatter has no ONNX form) and the encoder's recurrent states in; the flow and the new states out.
The torch step is the path ``predict`` runs (compiled gate kernels, channels-last)."""

from __future__ import annotations

import os
import tempfile
import warnings

import numpy as np
import torch

from agents.flownet import normalise_input, pad_to_multiple
from losses.kernel_switch import set_cpu_kernels
from losses.warp import forward_warp_flow

__all__ = ["NetworkStep"]


class _Core(torch.nn.Module):
    """The network's forward without the prior's alignment: (padded input, aligned prior in network
    units, *states) -> (finest flow in network units, *new states)."""

    def __init__(self, model, keys) -> None:
        super().__init__()
        self.model, self.keys = model, list(keys)

    def forward(self, padded, prior, *states):
        state, new = dict(zip(self.keys, states)), {}
        skips = self.model.encode(padded, state, new)
        residual = self.model.bottleneck(skips[-1], state, new)
        flows = self.model.decode(residual, skips, prior, state, new)
        return (flows[-1], *(new[k] for k in self.keys))


class NetworkStep:
    """The second step of ``model`` (an FGD-Net style network: EV-MGRFlowNet and its kin) on a
    sparse random input of ``size``: torch's step and, on demand, onnxruntime's."""

    def __init__(self, model, size: tuple[int, int], seed: int = 0) -> None:
        self.model = model.eval()
        generator = torch.Generator().manual_seed(seed)
        shape = (1, model.in_channels, *size)
        self.x = torch.rand(shape, generator=generator) * (torch.rand(shape, generator=generator) < 0.05)
        with torch.no_grad():
            _, self.state = model(self.x, None)
        self.keys = [k for k in self.state if k != "prior_flow"]

    def run_torch(self) -> np.ndarray:
        """The step as predict runs it; the flow in pixels."""
        with torch.no_grad():
            flows, _ = self.model(self.x, self.state)
        return flows[-1][0].numpy()

    def _feed(self) -> dict:
        padded = pad_to_multiple(normalise_input(self.x, self.model.input_norm))
        prior = pad_to_multiple(forward_warp_flow(self.state["prior_flow"]) / self.model.flow_scaling)
        return {"x": padded.numpy(), "prior": prior.numpy(), **{k: self.state[k].numpy() for k in self.keys}}

    def onnxruntime_runner(self, threads: int = 1):
        """A callable running the step in onnxruntime (the prior aligned by torch, as in
        :meth:`run_torch`), flow in pixels; ImportError without onnxruntime."""
        import onnxruntime

        padded = torch.as_tensor(self._feed()["x"])
        inputs = (padded, torch.as_tensor(self._feed()["prior"]), *(self.state[k] for k in self.keys))
        core = _Core(self.model, self.keys)
        previous_layout, previous_kernels = getattr(self.model, "channels_last", None), set_cpu_kernels(False)
        self.model.channels_last = False  # the torch expressions (the compiled kernels have no ONNX form)
        try:
            with tempfile.TemporaryDirectory() as tmp, warnings.catch_warnings():
                warnings.simplefilter("ignore")  # the exporter's notes on tracing and constant folding
                path = os.path.join(tmp, "step.onnx")
                torch.onnx.export(core, inputs, path, dynamo=False, opset_version=17,
                                  input_names=["x", "prior", *self.keys],
                                  output_names=["flow", *(f"new_{k}" for k in self.keys)])
                options = onnxruntime.SessionOptions()
                options.intra_op_num_threads, options.inter_op_num_threads = int(threads), 1
                session = onnxruntime.InferenceSession(path, options, providers=["CPUExecutionProvider"])
        finally:
            self.model.channels_last = previous_layout
            set_cpu_kernels(previous_kernels)
        names = {i.name for i in session.get_inputs()}
        height, width = self.x.shape[-2:]
        scale = float(self.model.flow_scaling)

        def run() -> np.ndarray:
            feed = {k: v for k, v in self._feed().items() if k in names}
            return session.run(["flow"], feed)[0][0, :, :height, :width] * scale

        self._ort = run
        return run

    def parity(self) -> float:
        """Largest difference in pixels between the two steps' flows."""
        return float(np.abs(self._ort() - self.run_torch()).max())
