"""The CUDA path against the CPU: every network's forward and backward, the losses and their
gradients, two training steps (float32 and bf16 autocast), evaluate and predict with
``--device cuda``, and a 2-process NCCL run that stops and resumes.

Skipped, with the reason printed (``pytest -ra``), where torch sees no CUDA device; the NCCL test
also needs two GPUs (NCCL refuses two ranks on one GPU). On a machine with a GPU this module is
the first step of ``bash scripts/device_check.sh``. The same computations run on the CPU with the
compiled kernels switched off in tests/test_kernels_off.py on every machine.

Tolerances: TF32 is switched off here, so CUDA computes in float32 like the CPU; what remains is
summation order (cuDNN's algorithms, atomics in scatter_add / index_add), a few 1e-6 relative.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from agents.checkpoint import load_checkpoint
from tests.device_parity import MODEL_NAMES, loss_run, network_run, relative_error, training_run
from tests.recordings import write_translating_recording

ROOT = Path(__file__).resolve().parents[1]

pytestmark = pytest.mark.skipif(
    not torch.cuda.is_available(),
    reason=f"no CUDA device (torch {torch.__version__}, built for CUDA {torch.version.cuda}): the CUDA path is "
           "checked on the CPU by tests/test_kernels_off.py; on a GPU run bash scripts/device_check.sh",
)


@pytest.fixture(autouse=True)
def _no_tf32():
    """Float32 convolutions and matrix products as on the CPU (TF32 would round to 10 bits)."""
    saved = torch.backends.cudnn.allow_tf32, torch.backends.cuda.matmul.allow_tf32
    torch.backends.cudnn.allow_tf32 = torch.backends.cuda.matmul.allow_tf32 = False
    yield
    torch.backends.cudnn.allow_tf32, torch.backends.cuda.matmul.allow_tf32 = saved


@pytest.fixture(scope="module")
def recordings(tmp_path_factory):
    folder = tmp_path_factory.mktemp("cuda-data")
    return [write_translating_recording(folder / f"dots{i}.h5", np.random.default_rng(10 + i), sensor_size=(32, 32),
                                        velocity=(200.0 - 150 * i, -100.0 + 50 * i)) for i in range(2)]


@pytest.mark.parametrize("name", MODEL_NAMES)
def test_networks_forward_and_backward_match_cpu(name):
    cpu, cuda = network_run(name, "cpu"), network_run(name, "cuda")
    np.testing.assert_allclose(cuda["flows"].numpy(), cpu["flows"].numpy(), rtol=1e-4, atol=1e-5 * 16)
    assert relative_error(cuda["grads"], cpu["grads"]) < 1e-4


@pytest.mark.parametrize("name", ["ev-mgrflownet", "convgru-ev-flownet"])
def test_bf16_autocast_stays_near_float32(name):
    """bf16 keeps 8 bits of mantissa: the flows within a few percent, the state carried in float32."""
    cpu = network_run(name, "cpu")
    bf16 = network_run(name, "cuda", autocast=torch.bfloat16)
    assert bf16["flows"].dtype == torch.float32 and torch.isfinite(bf16["grads"]).all()
    assert relative_error(bf16["flows"], cpu["flows"]) < 0.05
    assert relative_error(bf16["grads"], cpu["grads"]) < 0.1


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_losses_and_gradients_match_cpu(dtype):
    cpu, cuda = loss_run("cpu", dtype=dtype), loss_run("cuda", dtype=dtype)
    rtol, grad_tol = (1e-9, 1e-9) if dtype == torch.float64 else (1e-4, 1e-3)
    for key in cpu:
        np.testing.assert_allclose(cuda[key][0].numpy(), cpu[key][0].numpy(), rtol=rtol, atol=rtol * 1e-3, err_msg=key)
        assert relative_error(cuda[key][1], cpu[key][1]) < grad_tol, key


def test_two_training_steps_match_cpu(recordings):
    cpu = training_run(recordings[0], "cpu", amp="off")
    cuda = training_run(recordings[0], "cuda", amp="off")
    np.testing.assert_allclose(cuda["losses"], cpu["losses"], rtol=1e-4)
    assert relative_error(cuda["weights"], cpu["weights"]) < 1e-4
    # mixed precision: the first loss (same weights) within bf16's / fp16's rounding; fp16's loss
    # scaling may skip a step on an overflow, so later losses are only checked to be finite
    amps = ["bf16"] + (["fp16"] if torch.cuda.get_device_capability()[0] >= 7 else [])  # bf16: what --amp auto picks
    for amp in amps:
        mixed = training_run(recordings[0], "cuda", amp=amp)
        assert np.isfinite(mixed["losses"]).all(), amp
        assert mixed["losses"][0] == pytest.approx(cpu["losses"][0], rel=0.02), amp


def test_evaluate_and_predict_on_cuda_match_cpu(recordings, tmp_path):
    from evflow_cli.commands import evaluate as evaluate_script
    from evflow_cli.commands import predict as predict_script
    from evflow_cli.commands import train as train_script

    run = tmp_path / "run"
    train_script.main(["--data", str(recordings[0]), "--width", "4", "--num-envs", "1", "--unroll", "2", "--steps", "2",
                       "--out", str(run), "--val-data", "", "--no-progress", "--device", "cuda", "--amp", "off"])
    results, summaries = [], []
    for k, device in enumerate(("cpu", "cuda")):
        evaluate_script.main(["--checkpoint", str(run / "checkpoint.pt"), "--data", str(recordings[1]), "--dt", "1",
                              "--out", str(tmp_path / f"ev{k}"), "--pictures", "0", "--no-progress", "--device", device])
        results.append(json.loads((tmp_path / f"ev{k}" / "results.json").read_text())["overall"]["dt1"])
        predict_script.main([str(recordings[1]), "--model", str(run / "checkpoint.pt"), "--out",
                             str(tmp_path / f"flow{k}.h5"), "--no-video", "--no-progress", "--device", device,
                             "--json", str(tmp_path / f"predict{k}.json")])
        summaries.append(json.loads((tmp_path / f"predict{k}.json").read_text()))
    cpu, cuda = results
    assert cuda["windows"] == cpu["windows"] > 0
    for key in ("aee", "hmc"):
        assert cuda[key] == pytest.approx(cpu[key], rel=1e-4), key
    assert summaries[1]["windows"] == summaries[0]["windows"] > 0
    for key in ("aee", "hmc"):
        assert summaries[1][key] == pytest.approx(summaries[0][key], rel=1e-4), key


@pytest.mark.skipif(torch.cuda.device_count() < 2 or not torch.distributed.is_nccl_available(),
                    reason="needs 2 CUDA devices and NCCL (NCCL refuses two ranks on one GPU)")
def test_two_nccl_processes_resume_each_its_own_episodes(recordings, tmp_path):
    """As tests/test_distributed.py on gloo: stop at 3 of 6 steps, resume; each rank rolls over the
    uninterrupted run's windows, the losses within CUDA's summation order."""
    common = ["--data", *map(str, recordings), "--model", "convgru-ev-flownet", "--width", "4", "--num-envs", "2",
              "--unroll", "3", "--val-data", str(recordings[0]), "--val-windows", "2", "--no-progress",
              "--ckpt-every", "100", "--lr", "1e-3", "--device", "cuda", "--amp", "off"]
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": str(ROOT)}

    def torchrun(args):
        cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node=2",
               str(ROOT / "tests" / "ddp_record.py"), *args]
        done = subprocess.run(cmd, capture_output=True, text=True, timeout=600, env=env)
        assert done.returncode == 0, done.stderr[-4000:]

    full, part = tmp_path / "full", tmp_path / "part"
    torchrun(common + ["--steps", "6", "--out", str(full)])
    torchrun(common + ["--steps", "3", "--out", str(part)])
    assert load_checkpoint(part / "checkpoint.pt")["world_size"] == 2
    torchrun(["--resume", "--steps", "6", "--out", str(part), "--val-data", str(recordings[0]), "--val-windows", "2",
              "--no-progress", "--device", "cuda"])
    for rank in (0, 1):
        records = [[json.loads(line) for line in (out / f"windows-rank{rank}.jsonl").read_text().splitlines()]
                   for out in (full, part)]
        assert [r["windows"] for r in records[1]] == [r["windows"] for r in records[0]]
        np.testing.assert_allclose([r["loss"] for r in records[1]], [r["loss"] for r in records[0]], rtol=1e-4)


def test_the_unrolled_finish_and_its_second_order_gradient_match_cpu(rng):
    """Training for the finish (losses.unrolled_finish, --finish-steps): the finished flow and the
    gradient through the unrolled steps on CUDA against the CPU."""
    from losses import EventBatch, unrolled_finish, window_loss
    from tests.recordings import translating_dots

    events, (t0, t1) = translating_dots(rng, sensor_size=(48, 64), duration_us=66_666, num_dots=80,
                                        events_per_s=100_000)
    window = {**events.as_dict(), "t_start": t0, "t_end": t1}
    results = {}
    for device in ("cpu", "cuda"):
        batch = EventBatch.from_windows([window], device=device)
        proposal = torch.full((1, 2, 48, 64), 0.7, device=device, requires_grad=True)
        finished = unrolled_finish(proposal, batch, steps=3, lr=0.6)
        (gradient,) = torch.autograd.grad(window_loss(finished, batch).loss, proposal)
        results[device] = (finished.detach().cpu(), gradient.cpu())
    assert relative_error(results["cuda"][0], results["cpu"][0]) < 1e-4
    assert relative_error(results["cuda"][1], results["cpu"][1]) < 1e-3
