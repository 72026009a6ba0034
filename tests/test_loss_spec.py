"""One loss specification (losses.LossSpec) for the env's reward, training, the solver and the
teacher; the loss's terms registered by name (losses.terms.TERMS)."""

import dataclasses

import numpy as np
import pytest
import torch

import agents.cmax as cmax_module
import agents.objectives as objectives_module
import agents.teacher as teacher_module
import envs.env as env_module
from agents.cmax import CMaxSettings
from agents.objectives import RolloutWindow, make_objective
from agents.teacher import TeacherSettings
from agents.train_config import TrainConfig
from envs.env import EventFlowEnv
from losses import (
    TERMS,
    EventBatch,
    LossSpec,
    LossWeights,
    Term,
    accumulated_hmc_loss,
    accumulated_window_loss,
    sample_flow,
    window_loss,
    zero_flow_loss,
)

#: settings that differ from every default
OPTIONS = dict(lambda_1=0.7, lambda_2=0.02, alpha=0.5, border_penalty=2.0, border_ramp=4.0)


def test_spec_round_trips_validates_and_keeps_the_old_name():
    spec = LossSpec(**OPTIONS, loss="at")
    assert LossSpec.from_dict(spec.to_dict()) == spec and spec.to_dict()["loss"] == "at"
    assert LossSpec.from_dict({"lambda_2": 0.5}) == LossSpec(lambda_2=0.5)
    assert LossWeights(0.7, 0.02, 0.5, 2.0, 4.0) == LossSpec(**OPTIONS)  # the weights' positional order
    assert LossSpec.from_options(TrainConfig(**OPTIONS)) == LossSpec(**OPTIONS)
    assert LossSpec.from_options({"lambda_1": 0.7, "lr": 1.0}, lambda_2=None) == LossSpec(lambda_1=0.7)
    with pytest.raises(ValueError, match=r"unknown settings \['lambda_3'\]"):
        LossSpec.from_dict({"lambda_3": 1.0})
    with pytest.raises(ValueError, match=r"loss must be one of \('hmc', 'at'\), got 'l1'"):
        LossSpec(loss="l1")
    for name, bad in (("border_ramp", -1.0), ("border_ramp", float("inf")), ("lambda_1", -0.1),
                      ("lambda_2", float("nan")), ("border_penalty", -1.0), ("alpha", float("inf"))):
        with pytest.raises(ValueError, match=name):
            LossSpec(**{name: bad})
    with pytest.raises(dataclasses.FrozenInstanceError):
        spec.lambda_1 = 1.0


def test_the_env_takes_the_spec_whole_or_its_settings_not_both():
    spec = LossSpec(**OPTIONS, loss="at")
    by_keywords = EventFlowEnv("synthetic-mini", loss="at", **OPTIONS)
    whole = EventFlowEnv("synthetic-mini", loss_spec=spec)
    assert by_keywords.loss_spec == whole.loss_spec == spec and whole.loss_spec is spec
    assert (whole.loss_name, whole.loss_weights) == ("at", spec)
    with pytest.raises(ValueError, match=r"not both"):
        EventFlowEnv("synthetic-mini", loss_spec=spec, lambda_2=0.1)
    with pytest.raises(ValueError, match="border_ramp"):
        EventFlowEnv("synthetic-mini", border_ramp=-1.0)


def _spy(monkeypatch, module, name, result, seen):
    """Replace ``module.name`` by a function that records its loss spec and returns ``result(args)``."""
    original = getattr(module, name)

    def spy(*args, **kwargs):
        seen.append(kwargs["weights"] if "weights" in kwargs else args[2])
        return result(original, *args, **kwargs)

    monkeypatch.setattr(module, name, spy)


def test_env_training_solver_and_teacher_score_with_one_spec_built_from_the_same_options(monkeypatch):
    """Built from the same options, the env's reward, the per-window training objective, the
    contrast-maximisation solver and the teacher (its targets' solver and the in-update one,
    with the same smoothness weight) all score windows with equal specs."""
    expected = LossSpec(**OPTIONS)
    env = EventFlowEnv("synthetic-mini", **OPTIONS)
    _, info = env.reset(seed=0)
    window, (H, W) = info["window"], (env.height, env.width)
    seen = {part: [] for part in ("env", "training", "solver", "teacher", "teacher objective")}
    passthrough = lambda original, *args, **kwargs: original(*args, **kwargs)  # noqa: E731
    solved = lambda original, events, height, width, **kwargs: torch.zeros(events.x.shape[0], 2, height, width)  # noqa: E731
    _spy(monkeypatch, env_module, "window_loss", passthrough, seen["env"])
    _spy(monkeypatch, objectives_module, "window_loss", passthrough, seen["training"])
    _spy(monkeypatch, cmax_module, "contrast_maximisation_flow", solved, seen["solver"])
    _spy(monkeypatch, teacher_module, "contrast_maximisation_flow", solved, seen["teacher"])
    _spy(monkeypatch, objectives_module, "contrast_maximisation_flow", solved, seen["teacher objective"])

    env.step(np.zeros(env.action_space.shape, np.float32))
    cfg = TrainConfig(data="synthetic-mini", num_envs=1, **OPTIONS, teacher_lambda_2=OPTIONS["lambda_2"])
    batch = EventBatch.from_windows([window])
    flows = [torch.zeros(1, 2, H, W)]
    rollout = [RolloutWindow(flows, batch, zero_flow_loss(flows[-1], batch, cfg.loss_spec), {"window": [window]})]
    make_objective(cfg, 32.0)(rollout)
    CMaxSettings(**OPTIONS).solve(window, (H, W))
    teacher_module._solve_coarse(batch, H, W, TeacherSettings(**OPTIONS), lr=0.05, counts=[len(window.events.t)])
    teacher = dataclasses.replace(cfg, loss="teacher")
    make_objective(teacher, 32.0, device=torch.device("cpu"), height=H, width=W)(rollout)
    assert {part: specs for part, specs in seen.items()} == {part: [expected] for part in seen}


def _speed(x):
    """A term for the test: the mean squared flow at the valid events, (B,) (0 under zero flow)."""
    mask = x.events.mask.to(x.u.dtype)
    return (x.u.square().sum(dim=2) * mask).sum(dim=1) / mask.sum(dim=1).clamp_min(1)


def test_a_registered_term_adds_exactly_its_weight_times_its_value(monkeypatch):
    env = EventFlowEnv("synthetic-mini")
    _, info = env.reset(seed=0)
    windows = [info["window"]]
    for _ in range(2):
        _, _, _, _, info = env.step(np.zeros(env.action_space.shape, np.float32))
        windows.append(info["window"])
    events = EventBatch.from_windows(windows, dtype=torch.float64)
    flow = torch.randn(3, 2, env.height, env.width, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    spec = LossSpec(**OPTIONS)
    before = window_loss(flow, events, spec)
    zero_before = zero_flow_loss(flow, events, spec)
    monkeypatch.setitem(TERMS, "speed", Term(_speed, "lambda_1"))
    after = window_loss(flow, events, spec)
    padded = events.zero_padding()
    u = sample_flow(flow, padded.x, padded.y, padded.mask)
    mask = padded.mask.to(u.dtype)
    term = (u.square().sum(dim=2) * mask).sum(dim=1) / mask.sum(dim=1).clamp_min(1)
    assert torch.equal(zero_flow_loss(flow, events, spec).per_sample, zero_before.per_sample)  # 0 under zero flow
    assert torch.equal(after.per_sample, before.per_sample + OPTIONS["lambda_1"] * term)
    assert torch.equal(after.components["speed"], term)
    # a term of L_HMC alone leaves L_AT as it was; one whose weight the spec does not give weighs 0
    at = LossSpec(**OPTIONS, loss="at")
    monkeypatch.setitem(TERMS, "speed", Term(_speed, "lambda_1", losses=("hmc",)))
    with_term = window_loss(flow, events, at).per_sample
    monkeypatch.setitem(TERMS, "speed", Term(_speed, "lambda_3", logged=False))
    assert torch.equal(window_loss(flow, events, spec).per_sample, before.per_sample)
    monkeypatch.delitem(TERMS, "speed")
    assert torch.equal(with_term, window_loss(flow, events, at).per_sample)


def test_accumulated_window_loss_is_the_accumulated_loss_with_the_border_rule():
    env = EventFlowEnv("synthetic-mini")
    _, info = env.reset(seed=0)
    batches = []
    for _ in range(3):
        batches.append(EventBatch.from_windows([info["window"]], dtype=torch.float64))
        _, _, _, _, info = env.step(np.zeros(env.action_space.shape, np.float32))
    generator = torch.Generator().manual_seed(1)
    flows = [[torch.randn(1, 2, env.height, env.width, dtype=torch.float64, generator=generator) * 4] for _ in batches]
    spec = LossSpec(**OPTIONS)
    kwargs = dict(lambda_1=spec.lambda_1, lambda_2=spec.lambda_2, alpha=spec.alpha, border_ramp=spec.border_ramp,
                  flow_scaling=32.0)
    zero = accumulated_hmc_loss([[torch.zeros_like(f[-1])] for f in flows], batches, **kwargs).per_sample
    weight = spec.border_penalty * zero
    expected = accumulated_hmc_loss(flows, batches, border_penalty=weight, outside_weight=weight, **kwargs)
    out = accumulated_window_loss(flows, batches, spec, flow_scaling=32.0)
    assert torch.equal(out.per_sample, expected.per_sample)
    assert out.components.keys() == expected.components.keys()
    bare = dataclasses.replace(spec, border_penalty=0.0)
    assert torch.equal(accumulated_window_loss(flows, batches, bare, flow_scaling=32.0).per_sample,
                       accumulated_hmc_loss(flows, batches, **kwargs).per_sample)
    with pytest.raises(ValueError, match="L_HMC"):
        accumulated_window_loss(flows, batches, dataclasses.replace(spec, loss="at"))
