"""agents/objectives.py: the teacher's endpoint error against the obvious form with torch's norm."""

import pytest
import torch

from agents.objectives import _endpoint_error


def _reference(flow, target, weight):
    return ((flow - target).norm(dim=1, keepdim=True) * weight).sum() / weight.sum().clamp_min(1)


def test_endpoint_error_matches_the_norm_in_value_and_gradient():
    generator = torch.Generator().manual_seed(0)
    flow = torch.randn(3, 2, 9, 11, generator=generator, dtype=torch.float64) * 4
    target = torch.randn(3, 2, 9, 11, generator=generator, dtype=torch.float64) * 4
    target[0, :, 2, 3] = flow[0, :, 2, 3]  # a pixel where flow and target agree exactly
    weight = (torch.rand(3, 1, 9, 11, generator=generator) < 0.7).double()
    mine, theirs = flow.clone().requires_grad_(), flow.clone().requires_grad_()
    ours, reference = _endpoint_error(mine, target, weight), _reference(theirs, target, weight)
    ours.backward()
    reference.backward()
    torch.testing.assert_close(ours, reference, rtol=1e-12, atol=0)
    assert torch.isfinite(mine.grad).all()
    assert (mine.grad[0, :, 2, 3] == 0).all()  # the norm's gradient at zero length, not 0 x inf
    torch.testing.assert_close(mine.grad, theirs.grad, rtol=1e-10, atol=1e-15)


def test_endpoint_error_of_float32_teacher_sizes_agrees_with_the_norm():
    generator = torch.Generator().manual_seed(1)
    flow, target = (torch.randn(8, 2, 96, 96, generator=generator) * 3 for _ in range(2))
    weight = torch.ones(8, 1, 96, 96)
    torch.testing.assert_close(_endpoint_error(flow, target, weight), _reference(flow, target, weight),
                               rtol=1e-6, atol=0)


def test_settings_that_would_train_another_loss_than_named_are_refused():
    """L_AT has no accumulated mode: the pair trained L_HMC without a word; now it is refused, as
    the unrolled finish is beside the accumulated loss."""
    from agents.train_config import TrainConfig

    with pytest.raises(ValueError, match="exists for --loss hmc alone: --loss at takes --loss-mode window"):
        TrainConfig(loss="at", loss_mode="accumulated")
    with pytest.raises(ValueError, match="--finish-steps finishes each window's flow"):
        TrainConfig(loss="hmc", loss_mode="accumulated", finish_steps=2)
    assert TrainConfig(loss="at").loss_mode == "window" and TrainConfig(loss="hmc", loss_mode="accumulated")
