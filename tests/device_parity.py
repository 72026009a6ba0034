"""The same computations on any device, results on the CPU: what tests/test_kernels_off.py runs on
both CPU paths (compiled kernels on and off) and tests/test_cuda.py on CUDA and the CPU.

Every function builds its inputs and weights on the CPU from a seed and moves them to ``device``,
so two calls differ only in where (and along which path) the arithmetic ran.
"""

from __future__ import annotations

import numpy as np
import torch

from agents import make_model
from agents.learner import Learner, TrainConfig
from agents.registry import MODELS
from losses import EventBatch, accumulated_hmc_loss, at_loss, forward_warp_flow, hmc_loss

#: every built-in network
MODEL_NAMES = sorted(MODELS)


def count_images(batch: int, height: int, width: int, seed: int, channels: int = 2) -> torch.Tensor:
    """(batch, channels, height, width) float32 sparse random event counts."""
    generator = torch.Generator().manual_seed(seed)
    counts = torch.randint(0, 4, (batch, channels, height, width), generator=generator).float()
    return counts * (torch.rand(batch, 1, height, width, generator=generator) < 0.3)


def network_run(name: str, device: str, *, windows: int = 2, batch: int = 2, size=(24, 40), autocast=None) -> dict:
    """Model ``name`` (base width 4, seeded weights) over ``windows`` windows with its state carried;
    loss = the sum over windows and scales of the mean squared flow. Returns the finest flow of
    each window ``flows`` (windows, B, 2, H, W) and every parameter's gradient ``grads`` (flat),
    float32 on the CPU."""
    from agents import RecurrentPolicy

    torch.manual_seed(0)
    model = make_model(name, base_width=4, flow_scaling=16.0)
    policy = RecurrentPolicy(model, device=device, autocast=autocast)
    finest, loss = [], 0.0
    for k in range(windows):
        flows = policy(count_images(batch, *size, seed=k, channels=getattr(model, "in_channels", 2)).to(device))
        finest.append(flows[-1])
        loss = loss + sum(flow.square().mean() for flow in flows)
    loss.backward()
    grads = torch.cat([p.grad.reshape(-1) for p in model.parameters() if p.grad is not None])
    return {"flows": torch.stack(finest).detach().float().cpu(), "grads": grads.detach().float().cpu()}


def _windows(rng: np.random.Generator, counts, height: int, width: int) -> list[dict]:
    windows = []
    for n in counts:
        t = np.sort(rng.integers(1000, 6001, n))
        windows.append(dict(x=rng.uniform(0, width - 1, n), y=rng.uniform(0, height - 1, n), t=t,
                            p=rng.choice([-1, 1], n), t_start=1000, t_end=6000))
    return windows


def loss_run(device: str, *, dtype=torch.float32, scale: float = 3.0) -> dict:
    """The losses on random events (a window with none among them) and a random flow: per-sample
    values and the gradient of a weighted sum, for L_HMC with the border rule, L_AT, accumulated
    L_HMC over two windows, and the forward warp of the flow; CPU float64 results."""
    rng = np.random.default_rng(7)
    height, width = 23, 31
    windows = _windows(rng, (300, 0, 450), height, width)
    later = _windows(rng, (200, 50, 10), height, width)
    flow0 = torch.from_numpy(rng.normal(0, scale, (3, 2, height, width))).to(dtype)
    weights = torch.arange(1, 4, dtype=dtype, device=device)
    out = {}

    def run(key, fn):
        flow = flow0.to(device).requires_grad_()
        per_sample = fn(flow)
        (per_sample * weights).sum().backward()
        out[key] = (per_sample.detach().double().cpu(), flow.grad.double().cpu())

    batch = EventBatch.from_windows(windows, dtype=dtype, device=device)
    batch2 = EventBatch.from_windows(later, dtype=dtype, device=device)
    run("hmc", lambda f: hmc_loss(f, batch, border_penalty=0.7, border_ramp=0.0).per_sample)
    run("at", lambda f: at_loss(f, batch).per_sample)
    run("accumulated", lambda f: accumulated_hmc_loss([f, 0.5 * f], [batch, batch2]).per_sample)
    run("forward_warp", lambda f: forward_warp_flow(f).square().mean(dim=(1, 2, 3)))
    return out


def training_run(recording, device: str, *, steps: int = 2, **config) -> dict:
    """``steps`` updates of EV-MGRFlowNet (width 4, 2 envs, 2 windows per update) on ``recording``:
    the logged losses and the final weights (flat, float32 on the CPU)."""
    cfg = TrainConfig(**{"data": str(recording), "width": 4, "num_envs": 2, "unroll": 2, "lr": 1e-3, "flips": False,
                         "device": device, **config})
    learner = Learner(cfg)
    try:
        losses = [learner.update()["loss"] for _ in range(steps)]
        weights = torch.cat([p.detach().reshape(-1) for p in learner.policy.model.parameters()]).float().cpu()
    finally:
        learner.close()
    return {"losses": losses, "weights": weights}


def relative_error(a: torch.Tensor, b: torch.Tensor) -> float:
    """|a - b| / |b| in the 2-norm (0 when both are 0)."""
    a, b = a.double(), b.double()
    norm = float(b.norm())
    return float((a - b).norm()) / norm if norm else float(a.norm())
