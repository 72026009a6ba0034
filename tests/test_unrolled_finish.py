"""losses.unrolled_finish (the finish training unrolls, ``--finish-steps``) against a plain loop
of the same solver written with finite differences: the same finished flow, and the same
derivative of the loss after the finish with respect to the proposal."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from envs.windows import Window
from losses import cpu_kernels, unrolled_finish, window_loss
from tests.recordings import translating_dots

H, W, GRID = 6, 8, 2


def _batch(rng):
    events, (t0, t1) = translating_dots(rng, sensor_size=(H, W), velocity=(60.0, -30.0), duration_us=33_333,
                                        num_dots=8, events_per_s=2_000)
    return Window.of(events, t0, t1).batch()


def _loss(flow, batch):
    return float(window_loss(flow, batch, flow_scaling=float(W)).per_sample.sum())


def _plain_loop(proposal, batch, steps, lr, h=1e-4):
    """The same updates with central finite differences for the gradient (no autograd)."""
    gh, gw = max(1, round(GRID * H / W)), GRID
    correction = torch.zeros(1, 2, gh, gw, dtype=torch.float64)

    def flow_of(c):
        return proposal + F.interpolate(c, size=(H, W), mode="bilinear", align_corners=False)

    for k in range(steps):
        gradient = torch.zeros_like(correction)
        for index in np.ndindex(*correction.shape):
            up, down = correction.clone(), correction.clone()
            up[index] += h
            down[index] -= h
            gradient[index] = (_loss(flow_of(up), batch) - _loss(flow_of(down), batch)) / (2 * h)
        correction = correction - lr * (1 - k / steps) * gradient / gradient.abs().mean().clamp_min(1e-12)
    return flow_of(correction)


def test_the_unrolled_finish_is_the_plain_loop_and_its_derivative_is_the_loops(rng):
    batch = _batch(rng)
    proposal = torch.tensor(np.stack([np.full((H, W), 1.2), np.full((H, W), -0.4)])[None], dtype=torch.float64)
    steps, lr = 2, 0.3
    finished = unrolled_finish(proposal, batch, steps=steps, lr=lr, grid=GRID, flow_scaling=float(W), create_graph=False)
    reference = _plain_loop(proposal, batch, steps, lr)
    assert torch.allclose(finished, reference, atol=2e-4)  # the same flow
    assert _loss(finished, batch) < _loss(proposal, batch)  # and the finish did its job
    # d loss(finish(proposal)) / d proposal through every step (second order included): the compiled
    # CPU kernels' double backward against torch's own autograd of the plain torch expressions
    # (the loss is piecewise smooth in the flow, so finite differences of the whole finish meet its
    # kinks; each piece is checked by the forward comparison above)
    gradients = {}
    for kernels in (True, False):
        with cpu_kernels(kernels):
            leaf = proposal.float().clone().requires_grad_()
            after = unrolled_finish(leaf, batch, steps=steps, lr=lr, grid=GRID, flow_scaling=float(W))
            (gradients[kernels],) = torch.autograd.grad(window_loss(after, batch, flow_scaling=float(W)).per_sample.sum(),
                                                        leaf)
            first_order = proposal.float().clone().requires_grad_()  # the finish's move held constant
            moved = first_order + (unrolled_finish(proposal.float(), batch, steps=steps, lr=lr, grid=GRID,
                                                   flow_scaling=float(W), create_graph=False) - proposal.float())
            (plain,) = torch.autograd.grad(window_loss(moved, batch, flow_scaling=float(W)).per_sample.sum(), first_order)
    assert torch.allclose(gradients[True], gradients[False], atol=1e-5)
    assert (gradients[False] - plain).abs().max() > 1e-3  # the unrolled steps' own derivative is in it


def test_no_steps_is_the_proposal_and_a_window_without_events_stays(rng):
    batch = _batch(rng)
    proposal = torch.ones(1, 2, H, W, dtype=torch.float64)
    assert unrolled_finish(proposal, batch, steps=0, lr=0.3) is proposal
    with pytest.raises(ValueError, match="steps"):
        unrolled_finish(proposal, batch, steps=-1, lr=0.3)


def test_training_takes_its_loss_after_the_finish(rng):
    from agents.learner import TrainConfig
    from agents.objectives import RolloutWindow, make_objective
    from losses import zero_flow_loss

    events, (t0, t1) = translating_dots(rng, sensor_size=(H, W), velocity=(60.0, -30.0), duration_us=66_666,
                                        num_dots=8, events_per_s=2_000)
    window = Window.of(events, t0, t1)  # two frames: the step doubles
    batch = window.batch()
    flow = torch.full((1, 2, H, W), 0.8, requires_grad=True)
    cfg = TrainConfig(num_envs=1, finish_steps=2, finish_lr=0.3, finish_grid=GRID, loss_scales="finest")
    zero = zero_flow_loss(flow.detach(), batch, cfg.weights, flow_scaling=float(W))
    loss, _ = make_objective(cfg, float(W))([RolloutWindow([flow], batch, zero, {"window": [window]})])
    finished = unrolled_finish(flow, batch, steps=2, lr=0.6, grid=GRID, flow_scaling=float(W), weights=cfg.weights)
    expected = window_loss(finished, batch, cfg.weights, flow_scaling=float(W)).loss.item()
    assert loss.item() == pytest.approx(expected)
    alone, _ = make_objective(TrainConfig(num_envs=1, loss_scales="finest"), float(W))(
        [RolloutWindow([flow], batch, zero, {"window": [window]})])
    assert loss.item() != pytest.approx(alone.item())
    loss.backward()
    assert flow.grad is not None and flow.grad.abs().sum() > 0
    with pytest.raises(ValueError, match="--finish-steps"):
        TrainConfig(finish_steps=2, loss_mode="accumulated")
