"""Networks, their state semantics and the policy wrapper (agents/).

Most tests run at the CPU width (base width 8); the paper width only where no forward pass is
needed (parameter counts) or a single small one is.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from agents import (
    MODELS,
    WIDTHS,
    EVMGRFlowNet,
    ModelLoadError,
    RecurrentPolicy,
    check_protocol,
    make_model,
)
from agents.evmgrflownet import DeepMemoryUp
from agents.layers import ConvGRU, STConvGRU
from agents.spiking import arctan_spike
from evflow_cli.summary import MODEL_VARIANTS, count_parameters, forward_flops, parameter_table

BUILT_IN = ["ev-mgrflownet", "ev-flownet", "convgru-ev-flownet", "xlif-ev-flownet", "unet-feedforward", "unet-convgru",
            "unet-xlif-encoder"]
RECURRENT = ["ev-mgrflownet", "convgru-ev-flownet", "xlif-ev-flownet", "unet-convgru", "unet-xlif-encoder"]
SCALING = 128.0


def count_images(batch: int, height: int, width: int, seed: int = 0) -> torch.Tensor:
    """(B, 2, H, W) float32 sparse event counts."""
    generator = torch.Generator().manual_seed(seed)
    counts = torch.randint(0, 4, (batch, 2, height, width), generator=generator).float()
    keep = torch.rand(batch, 1, height, width, generator=generator) < 0.3
    return counts * keep


def build(name: str, seed: int = 0, **kwargs) -> torch.nn.Module:
    """A CPU-width model reading 2-channel count images (EV-FlowNet's count-only variant)."""
    torch.manual_seed(seed)
    return make_model(name, width="cpu", **{"in_channels": 2, **kwargs})


@pytest.fixture(scope="module")
def cpu_models() -> dict[str, torch.nn.Module]:
    return {name: build(name) for name in BUILT_IN}


# ---------------------------------------------------------------- shapes and ranges


@pytest.mark.parametrize("size", [(128, 128), (256, 256), (260, 346)])
@pytest.mark.parametrize("batch", [1, 4])
@pytest.mark.parametrize("name", BUILT_IN)
def test_shapes_finite_and_bounded(cpu_models, name, batch, size):
    model = cpu_models[name]
    height, width = size
    state = None
    with torch.no_grad():
        for window in range(2):  # the second window runs the recurrent paths
            flows, state = model(count_images(batch, height, width, seed=window), state)
            assert len(flows) == 4
            for flow, stride in zip(flows, [8, 4, 2, 1]):
                assert flow.shape == (batch, 2, math.ceil(height / stride), math.ceil(width / stride))
                assert flow.dtype == torch.float32
                assert torch.isfinite(flow).all()
                assert flow.abs().max() <= SCALING * (1 + 1e-6)
            assert flows[-1].shape[-2:] == size
            assert all(v.shape[0] == batch for v in state.values())


@pytest.mark.parametrize("kwargs", [{"use_st_convgru": False}, {"use_prior_flow": False}])
def test_ablations_run_and_keep_the_interface(kwargs):
    model = build("ev-mgrflownet", **kwargs)
    with torch.no_grad():
        flows, state = model(count_images(2, 36, 52), None)
        flows, state = model(count_images(2, 36, 52, seed=1), state)
    assert flows[-1].shape == (2, 2, 36, 52)
    assert ("prior_flow" in state) == kwargs.get("use_prior_flow", True)


def test_paper_width_single_small_forward():
    model = make_model("ev-mgrflownet")  # paper width, c = 32
    assert model.base_width == 32
    with torch.no_grad():
        flows, state = model(count_images(1, 32, 48), None)
    assert flows[-1].shape == (1, 2, 32, 48)
    assert state["encoder4"].shape == (1, 16 * 32, 2, 3)


def test_flow_scaling_bounds_outputs():
    model = build("ev-flownet", flow_scaling=4.0)
    with torch.no_grad():
        flows, _ = model(count_images(1, 32, 32) * 50, None)
    assert all(flow.abs().max() <= 4.0 for flow in flows)
    assert model.config["flow_scaling"] == 4.0


def test_stateless_model_returns_empty_state(cpu_models):
    _, state = cpu_models["ev-flownet"](count_images(1, 32, 32), None)
    assert state == {}


# ---------------------------------------------------------------- the zero-state rule


@pytest.mark.parametrize("name", BUILT_IN)
def test_all_zeros_state_is_a_fresh_sequence(cpu_models, name):
    model = cpu_models[name]
    x = count_images(2, 40, 56, seed=3)
    with torch.no_grad():
        _, state = model(count_images(2, 40, 56, seed=1), None)
        _, state = model(count_images(2, 40, 56, seed=2), state)
        fresh_flows, fresh_state = model(x, None)
        zero_flows, zero_state = model(x, {k: torch.zeros_like(v) for k, v in state.items()})
    for fresh, zeroed in zip(fresh_flows, zero_flows):
        assert torch.equal(fresh, zeroed)
    assert fresh_state.keys() == zero_state.keys()
    for key in fresh_state:
        assert torch.equal(fresh_state[key], zero_state[key]), key


@pytest.mark.parametrize("name", BUILT_IN)
def test_built_in_models_pass_the_protocol_check(cpu_models, name):
    check_protocol(cpu_models[name])


# ---------------------------------------------------------------- policy wrapper


def _clone(model: torch.nn.Module, name: str) -> torch.nn.Module:
    """A freshly built model (from its config) with the same weights."""
    fresh = make_model(name, **model.config)
    fresh.load_state_dict(model.state_dict())
    return fresh


@pytest.mark.parametrize("name", RECURRENT)
def test_reset_gives_a_fresh_model_output(cpu_models, name):
    policy = RecurrentPolicy(cpu_models[name])
    with torch.no_grad():
        for seed in range(3):
            policy(count_images(2, 32, 48, seed=seed))
        x = count_images(2, 32, 48, seed=9)
        continued = policy.model(x, policy.state)[0][-1]
        policy.reset()
        after_reset = policy(x)[-1]
        fresh = _clone(cpu_models[name], name)(x, None)[0][-1]
    assert torch.equal(after_reset, fresh)
    assert not torch.allclose(continued, fresh)  # the state mattered before the reset


@pytest.mark.parametrize("name", RECURRENT)
def test_reset_mask_resets_only_masked_elements(cpu_models, name):
    model = cpu_models[name]
    policy = RecurrentPolicy(model)
    with torch.no_grad():
        for seed in range(2):
            policy(count_images(3, 32, 48, seed=seed))
        kept_state = {k: v.clone() for k, v in policy.state.items()}
        x = count_images(3, 32, 48, seed=7)
        policy.reset(mask=np.array([True, False, True]))
        flows = policy(x)[-1]
        fresh = model(x, None)[0][-1]
        continued = model(x, kept_state)[0][-1]
    torch.testing.assert_close(flows[[0, 2]], fresh[[0, 2]], rtol=0, atol=1e-6)
    torch.testing.assert_close(flows[1], continued[1], rtol=0, atol=1e-6)
    assert not torch.allclose(flows[1], fresh[1])


def test_reset_mask_accepts_tensors_and_checks_length(cpu_models):
    policy = RecurrentPolicy(cpu_models["convgru-ev-flownet"])
    with torch.no_grad():
        policy(count_images(2, 32, 32))
        policy.reset(torch.tensor([False, True]))
        assert policy.state["encoder1"][1].abs().max() == 0
        assert policy.state["encoder1"][0].abs().max() > 0
        with pytest.raises(ValueError, match="mask"):
            policy.reset(np.array([True, False, True]))


@pytest.mark.parametrize("name", RECURRENT)
def test_detach_stops_backward_at_the_window_boundary(name):
    model = build(name)
    for detach in (False, True):
        policy = RecurrentPolicy(model)
        first = count_images(1, 32, 32, seed=1).requires_grad_(True)
        policy(first)
        if detach:
            policy.detach()
        flows = policy(count_images(1, 32, 32, seed=2))
        sum(flow.square().sum() for flow in flows).backward()
        if detach:
            assert first.grad is None
        else:
            assert first.grad is not None and first.grad.abs().sum() > 0


def test_act_single_and_vector_observations(cpu_models):
    model = cpu_models["ev-mgrflownet"]
    policy = RecurrentPolicy(model)
    image = count_images(1, 30, 40)[0].numpy()
    action = policy.act({"count_image": image})
    assert action.shape == (2, 30, 40) and action.dtype == np.float32
    with torch.no_grad():
        expected = model(torch.from_numpy(image)[None], None)[0][-1][0].numpy()
    np.testing.assert_array_equal(action, expected)
    assert policy.state["prior_flow"].requires_grad is False

    policy.reset()
    images = count_images(3, 30, 40).numpy()
    actions = policy.act({"count_image": images})
    assert actions.shape == (3, 2, 30, 40) and actions.dtype == np.float32
    with pytest.raises(ValueError, match="batch size changed"):
        policy.act({"count_image": images[:2]})


def test_policy_call_is_differentiable(cpu_models):
    policy = RecurrentPolicy(build("ev-mgrflownet"))
    flows = policy(count_images(2, 32, 32))
    assert flows[-1].requires_grad
    flows[-1].sum().backward()
    assert any(p.grad is not None for p in policy.parameters())


# ---------------------------------------------------------------- the recurrent paths are real


def _recurrent_path_parameters(model: EVMGRFlowNet) -> dict[str, torch.nn.Parameter]:
    """Parameters that only the carried state reaches: the M path's hidden side and the conv
    that builds M (ST-ConvGRU), and the hidden side of every FGD refinement ConvGRU."""
    named = {
        "deep_memory_up": model.deep_memory_up.conv.weight,
        "gru_deep.h_convs": model.grus[0].gru_deep.h_convs.weight,
    }
    for level, refiner in enumerate(model.decoder.refiners):
        named[f"refiner{level}.h_convs"] = refiner.h_convs.weight
    return named


def _gradients(model, windows: int) -> dict[str, torch.Tensor | None]:
    params = _recurrent_path_parameters(model)
    state = None
    for window in range(windows):
        flows, state = model(count_images(2, 32, 48, seed=window), state)
    weights = torch.randn(flows[-1].shape, generator=torch.Generator().manual_seed(0))
    loss = sum((flow * F.interpolate(weights, size=flow.shape[-2:])).sum() for flow in flows)
    grads = torch.autograd.grad(loss, list(params.values()), allow_unused=True)
    return dict(zip(params, grads))


def test_gradients_reach_m_path_and_refinement_at_the_second_window():
    model = build("ev-mgrflownet")
    first = _gradients(model, windows=1)
    second = _gradients(model, windows=2)
    for name, grad in first.items():  # fresh sequence: zero state, these weights are unused
        assert grad is None or grad.abs().max() == 0, name
    for name, grad in second.items():
        assert grad is not None and grad.abs().max() > 0, name
    # The M path's input-side weights (ConvGRU_b over X) and the fresh-estimate side of the
    # refiners are used at every window, so they must get gradients too.
    grads = torch.autograd.grad(
        model(count_images(1, 32, 32), None)[0][-1].sum(),
        [model.grus[0].gru_deep.x_convs.weight, model.decoder.refiners[3].x_convs.weight],
    )
    assert all(g.abs().max() > 0 for g in grads)


def test_ablation_switches_remove_those_parameters():
    without_st = build("ev-mgrflownet", use_st_convgru=False)
    without_prior = build("ev-mgrflownet", use_prior_flow=False)
    full_names = {n for n, _ in build("ev-mgrflownet").named_parameters()}
    st_names = {n for n in full_names if "deep" in n or "grus.0." in n}
    refine_names = {n for n in full_names if "refiners" in n}
    assert st_names and refine_names
    assert without_st.deep_memory_up is None and isinstance(without_st.grus[0], ConvGRU)
    assert not any("deep" in n for n, _ in without_st.named_parameters())
    assert without_prior.decoder.refiners is None
    assert not any("refiners" in n for n, _ in without_prior.named_parameters())
    assert "prior_flow" not in without_prior(count_images(1, 32, 32), None)[1]


# ---------------------------------------------------------------- layers against slow oracles


@pytest.mark.parametrize("low, size", [((16, 16), (128, 128)), ((3, 5), (24, 40)), ((5, 7), (13, 30))])
def test_deep_memory_up_equals_upsample_then_conv(low, size):
    torch.manual_seed(0)
    layer = DeepMemoryUp(12, 5).double()
    deepest = torch.randn(2, 12, *low, dtype=torch.float64, requires_grad=True)
    fast = layer(deepest, size)
    upsampled = F.interpolate(deepest, size=size, mode="bilinear", align_corners=False)
    slow = F.relu(F.conv2d(upsampled, layer.conv.weight, padding=1))  # conv_up by definition
    torch.testing.assert_close(fast, slow, rtol=1e-10, atol=1e-10)
    g_fast = torch.autograd.grad(fast.sum(), [deepest, layer.conv.weight])
    g_slow = torch.autograd.grad(slow.sum(), [deepest, layer.conv.weight])
    for a, b in zip(g_fast, g_slow):
        torch.testing.assert_close(a, b, rtol=1e-9, atol=1e-9)
    assert layer(torch.zeros(1, 12, *low, dtype=torch.float64), size).abs().max() == 0
    with torch.no_grad():  # channels-last in, channels-last out
        channels_last = layer(_cl(deepest), size)
    assert channels_last.is_contiguous(memory_format=CHANNELS_LAST)
    torch.testing.assert_close(channels_last, slow, rtol=1e-10, atol=1e-10)


def test_convgru_matches_equation_4():
    torch.manual_seed(0)
    gru = ConvGRU(3, 4).double()
    x = torch.randn(2, 3, 6, 7, dtype=torch.float64)
    h = torch.randn(2, 4, 6, 7, dtype=torch.float64)
    torch.testing.assert_close(gru(x, h), _gru_reference(gru, x, h))
    assert torch.equal(gru(x, None), gru(x, torch.zeros_like(h)))


def _gru_reference(gru: ConvGRU, x, h):
    """Eq. 4 written out with one convolution per weight matrix."""
    wx, bx = gru.x_convs.weight.chunk(3), gru.x_convs.bias.chunk(3)
    wh = gru.h_convs.weight.chunk(3)
    conv = lambda inp, w, b=None: F.conv2d(inp, w, b, padding=1)  # noqa: E731
    r = torch.sigmoid(conv(x, wx[0], bx[0]) + conv(h, wh[0]))
    z = torch.sigmoid(conv(x, wx[1], bx[1]) + conv(h, wh[1]))
    candidate = torch.tanh(r * conv(h, wh[2]) + conv(x, wx[2], bx[2]))
    return (1 - z) * h + z * candidate


def test_st_convgru_matches_equations_5_and_6():
    torch.manual_seed(0)
    layer = STConvGRU(4).double()
    x, own, deep = (torch.randn(2, 4, 6, 7, dtype=torch.float64) for _ in range(3))
    new_own = _gru_reference(layer.gru_own, x, own)  # eq. 5, S_k
    new_deep = _gru_reference(layer.gru_deep, x, deep)  # eq. 5, Mbar_k
    gate = torch.sigmoid(  # eq. 6, o_k = sig(Wfo*X + Wmo*Mbar_k + Wso*S_k)
        F.conv2d(x, layer.gate_input.weight, layer.gate_input.bias, padding=1)
        + F.conv2d(new_deep, layer.gate_hidden.weight[:, :4], padding=1)
        + F.conv2d(new_own, layer.gate_hidden.weight[:, 4:], padding=1)
    )
    fused = F.conv2d(torch.cat([new_deep, new_own], 1), layer.fusion.weight, layer.fusion.bias)
    out, carried = layer(x, own, deep)
    torch.testing.assert_close(carried, new_own)
    torch.testing.assert_close(out, gate * torch.tanh(fused))  # eq. 6, F_k
    zeros = torch.zeros_like(own)
    for a, b in zip(layer(x, None, None), layer(x, zeros, zeros)):
        assert torch.equal(a, b)


def test_arctan_spike_forward_step_and_surrogate_gradient():
    v = torch.tensor([-0.5, -0.01, 0.0, 0.01, 0.5], requires_grad=True)
    spikes = arctan_spike(v, 10.0)
    assert spikes.tolist() == [0.0, 0.0, 0.0, 1.0, 1.0]
    spikes.sum().backward()
    torch.testing.assert_close(v.grad, 1.0 / (1.0 + (10.0 * v.detach()) ** 2))


def test_xlif_encoder_spikes_and_learns():
    model = build("unet-xlif-encoder")
    flows, state = model(count_images(1, 32, 32) * 5, None)
    flows, state = model(count_images(1, 32, 32, seed=1) * 5, state)
    assert set(torch.unique(state["encoder1_z"]).tolist()) <= {0.0, 1.0}
    assert state["encoder1_z"].sum() > 0  # some neurons fire
    flows[-1].sum().backward()
    layer = model.neurons[0]
    for p in (layer.ff.weight, layer.leak, layer.t0, layer.t1, layer.trace_leak):
        assert p.grad is not None and torch.isfinite(p.grad).all()


# ---------------------------------------------------------------- registry, config, sizes


def test_registry_names_and_config_round_trip():
    assert set(BUILT_IN) <= set(MODELS)
    for name in BUILT_IN:
        model = build(name)
        assert model.base_width == WIDTHS["cpu"] == model.config["base_width"]
        rebuilt = make_model(name, **model.config)
        rebuilt.load_state_dict(model.state_dict())  # same architecture
    assert make_model("ev-mgrflownet", base_width=4, use_prior_flow=False).config == {
        "in_channels": 2,
        "base_width": 4,
        "flow_scaling": 128.0,
        "use_st_convgru": True,
        "use_prior_flow": False,
    }


def test_nonzero_rms_input_norm_against_a_per_sample_loop():
    from agents.flownet import normalise_input

    gen = torch.Generator().manual_seed(3)
    x = torch.randn(3, 5, 7, 9, generator=gen) * (torch.rand(3, 5, 7, 9, generator=gen) < 0.2)
    x[2] = 0.0  # a window without events stays zero
    out = normalise_input(x, "nonzero-rms")
    for b in range(3):
        values = x[b].numpy()[x[b].numpy() != 0]
        expected = x[b].numpy() / math.sqrt((values**2).mean()) if values.size else x[b].numpy()
        np.testing.assert_allclose(out[b].numpy(), expected, rtol=1e-6, atol=0)
    assert torch.equal(normalise_input(x, "none"), x)
    with pytest.raises(ValueError, match="input normalisation 'max'"):
        normalise_input(x, "max")


def test_input_norm_makes_the_flow_blind_to_the_events_per_pixel():
    """With nonzero-rms a window whose every event is repeated k times gives the same flow; the
    paper's input does not; the setting survives the config round trip and shapes no weight."""
    torch.manual_seed(0)
    normed = make_model("ev-mgrflownet", base_width=4, in_channels=5, input_norm="nonzero-rms")
    plain = make_model("ev-mgrflownet", base_width=4, in_channels=5)
    plain.load_state_dict(normed.state_dict())
    x = torch.randn(1, 5, 32, 32) * (torch.rand(1, 5, 32, 32) < 0.3)
    with torch.no_grad():
        torch.testing.assert_close(normed(3 * x, None)[0][-1], normed(x, None)[0][-1], rtol=1e-4, atol=1e-5)
        assert not torch.allclose(plain(3 * x, None)[0][-1], plain(x, None)[0][-1], rtol=1e-3, atol=1e-4)
    assert normed.config["input_norm"] == "nonzero-rms" and "input_norm" not in plain.config
    assert make_model("ev-mgrflownet", **normed.config).input_norm == "nonzero-rms"
    with pytest.raises(ValueError, match="unknown input_norm 'max'"):
        make_model("ev-mgrflownet", base_width=4, input_norm="max")


def test_unknown_names_and_bad_widths_fail_clearly():
    with pytest.raises(ModelLoadError, match="unknown model 'nope'"):
        make_model("nope")
    with pytest.raises(ValueError, match="width preset"):
        make_model("ev-flownet", width="huge")


def test_in_channels_is_a_parameter():
    model = build("convgru-ev-flownet", in_channels=5)
    flows, _ = model(torch.rand(1, 5, 32, 32), None)
    assert flows[-1].shape == (1, 2, 32, 32)
    with pytest.raises(ValueError, match="expected input"):
        model(torch.rand(1, 2, 32, 32), None)


def test_parameter_counts_at_paper_width():
    counts = dict(parameter_table("paper"))
    assert set(counts) == {label for label, _, _ in MODEL_VARIANTS}
    full = counts["EV-MGRFlowNet"]
    assert counts["ConvGRU-EV-FlowNet"] < counts["EV-MGRFlowNet w/o ST-ConvGRU"] < full
    assert counts["EV-MGRFlowNet w/o prior flows"] < full
    assert counts["EV-FlowNet"] < counts["ConvGRU-EV-FlowNet"]
    # Without both switches EV-MGRFlowNet is the project's ConvGRU U-Net (eq. 4 GRUs, 3x3 heads),
    # which differs from Hagenaars' ConvGRU-EV-FlowNet only in its heads (3x3 against 1x1).
    plain = make_model("ev-mgrflownet", use_st_convgru=False, use_prior_flow=False)
    assert count_parameters(plain) == count_parameters(make_model("unet-convgru"))
    head_difference = sum(2 * (9 - 1) * c for c in (256, 128, 64, 32))
    assert count_parameters(plain) - counts["ConvGRU-EV-FlowNet"] == head_difference


@pytest.mark.parametrize("name", ["ev-flownet", "convgru-ev-flownet"])
def test_forward_flops_equal_the_sum_over_convolutions(name):
    """forward_flops against 2 x (output elements) x (input channels) x 9 summed over every conv
    layer the window ran (these models call their convolutions only as modules)."""
    model = build(name)
    total = []

    def hook(module, inputs, output):
        weight = module.weight
        total.append(2 * output.numel() * weight.shape[1] * weight.shape[2] * weight.shape[3])

    flops = forward_flops(model, 2, 48, 64)  # before the hooks: its own two windows
    x = torch.zeros(2, 2, 48, 64)
    x[:, :, ::3, ::5] = 1.0
    with torch.no_grad():
        _, state = model(x, None)
        handles = [m.register_forward_hook(hook) for m in model.modules() if isinstance(m, torch.nn.Conv2d)]
        model(x, state)
    for handle in handles:
        handle.remove()
    assert flops == sum(total) > 0


# ---------------------------------------------------------------- channels-last and compiled gates

from agents import layers as agent_layers  # noqa: E402

CHANNELS_LAST = torch.channels_last


def _cl(t: torch.Tensor) -> torch.Tensor:
    return t.contiguous(memory_format=CHANNELS_LAST)


def _at_threads(threads: int, fn):
    """Run ``fn`` with torch (and so the compiled kernels) on ``threads`` threads."""
    before = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        return fn()
    finally:
        torch.set_num_threads(before)


def _count_gate_kernel_calls(monkeypatch) -> dict:
    calls = {"gru": 0, "gate": 0, "refiner": 0}
    gru_apply, gate_apply = agent_layers._GRUUpdates.apply, agent_layers._OutputGate.apply
    refiner_apply = agent_layers._RefinerUpdate.apply

    def gru(*args):
        calls["gru"] += 1
        return gru_apply(*args)

    def gate(*args):
        calls["gate"] += 1
        return gate_apply(*args)

    def refiner(*args):
        calls["refiner"] += 1
        return refiner_apply(*args)

    monkeypatch.setattr(agent_layers._GRUUpdates, "apply", gru)
    monkeypatch.setattr(agent_layers._OutputGate, "apply", gate)
    monkeypatch.setattr(agent_layers._RefinerUpdate, "apply", refiner)
    return calls


@pytest.mark.cpu_kernels  # the compiled kernels themselves (skipped with EVFLOW_CPU_KERNELS=0)
@pytest.mark.parametrize("threads", [1, 2])
@pytest.mark.parametrize("fresh", [False, True])
@pytest.mark.parametrize("hidden", [2, 5, 16])
def test_compiled_convgru_matches_equation_4(monkeypatch, hidden, fresh, threads):
    """Channels-last CPU tensors take the compiled update (both loop shapes: flat for small
    hidden sizes, per pixel row from 8 on); values and every gradient equal eq. 4 written out
    with one convolution per weight matrix (NCHW, torch)."""
    calls = _count_gate_kernel_calls(monkeypatch)
    torch.manual_seed(hidden)
    gru = ConvGRU(3, hidden).double()
    x = torch.randn(2, 3, 9, 11, dtype=torch.float64, requires_grad=True)
    h = torch.randn(2, hidden, 9, 11, dtype=torch.float64, requires_grad=True)
    weights = [gru.x_convs.weight, gru.x_convs.bias] + ([] if fresh else [gru.h_convs.weight])
    grad_out = torch.randn(2, hidden, 9, 11, dtype=torch.float64)
    inputs = [x] if fresh else [x, h]

    def compiled():
        out = gru(_cl(x), None if fresh else _cl(h))
        return out, torch.autograd.grad(out, inputs + weights, grad_out)

    out, grads = _at_threads(threads, compiled)
    assert calls["gru"] == 1
    expected = _gru_reference(gru, x, torch.zeros_like(h) if fresh else h)
    expected_grads = torch.autograd.grad(expected, inputs + weights, grad_out)
    torch.testing.assert_close(out, expected, rtol=1e-12, atol=1e-12)
    for got, want in zip(grads, expected_grads):
        torch.testing.assert_close(got, want, rtol=1e-10, atol=1e-12)


@pytest.mark.cpu_kernels  # the compiled kernels themselves (skipped with EVFLOW_CPU_KERNELS=0)
@pytest.mark.parametrize("threads", [1, 2])
@pytest.mark.parametrize("memories", ["both", "none", "own only"])
@pytest.mark.parametrize("channels", [3, 8])
def test_compiled_st_convgru_matches_equations_5_and_6(monkeypatch, channels, memories, threads):
    """The ST-ConvGRU on channels-last tensors (both GRUs from one input-side tensor, at column
    offsets 0 and 3C; the output gate in one pass) against its torch path, which
    test_st_convgru_matches_equations_5_and_6 ties to the equations."""
    calls = _count_gate_kernel_calls(monkeypatch)
    torch.manual_seed(channels)
    layer = STConvGRU(channels).double()
    x, own, deep = (torch.randn(2, channels, 7, 10, dtype=torch.float64, requires_grad=True) for _ in range(3))
    own_in = None if memories == "none" else own
    deep_in = deep if memories == "both" else None
    leaves = [x] + [t for t in (own_in, deep_in) if t is not None] + list(layer.parameters())
    grad_out = torch.randn(2, channels, 7, 10, dtype=torch.float64)
    grad_own = torch.randn(2, channels, 7, 10, dtype=torch.float64)

    def run(layout):
        out, carried = layer(*(None if t is None else layout(t) for t in (x, own_in, deep_in)))
        grads = torch.autograd.grad([out, carried], leaves, [grad_out, grad_own], allow_unused=True)
        return out, carried, grads

    out, carried, grads = _at_threads(threads, lambda: run(_cl))
    assert calls == {"gru": 1, "gate": 1, "refiner": 0}
    want_out, want_carried, want_grads = run(lambda t: t.contiguous())
    assert calls == {"gru": 1, "gate": 1, "refiner": 0}  # NCHW: torch
    torch.testing.assert_close(out, want_out, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(carried, want_carried, rtol=1e-12, atol=1e-12)
    for got, want in zip(grads, want_grads):
        if want is None:
            assert got is None or not got.abs().any()
        else:
            torch.testing.assert_close(got, want, rtol=1e-10, atol=1e-12)


@pytest.mark.cpu_kernels  # the compiled kernels themselves (skipped with EVFLOW_CPU_KERNELS=0)
@pytest.mark.parametrize("threads", [1, 2])
@pytest.mark.parametrize("fresh", [False, True])
def test_compiled_flow_refiner_matches_equations_10_and_11(monkeypatch, fresh, threads):
    """FGD-Net's refinement ``u = ConvGRU_flow(tanh(head), ubar)`` on a channels-last head (one
    merged convolution between two compiled passes) against eq. 4 written out with one
    convolution per weight matrix: values and the gradients of the head, the prior (through
    both the convolutions and the direct (1 - z) path) and every weight."""
    calls = _count_gate_kernel_calls(monkeypatch)
    torch.manual_seed(11)
    gru = ConvGRU(2, 2).double()
    head = torch.randn(3, 2, 9, 13, dtype=torch.float64, requires_grad=True)
    prior = torch.randn(3, 2, 9, 13, dtype=torch.float64, requires_grad=True)
    weights = [gru.x_convs.weight, gru.x_convs.bias] + ([] if fresh else [gru.h_convs.weight])
    inputs = [head] if fresh else [head, prior]
    grad_out = torch.randn(3, 2, 9, 13, dtype=torch.float64)

    def compiled():
        out = agent_layers.refine_flow(gru, _cl(head), None if fresh else prior)
        return out, torch.autograd.grad(out, inputs + weights, grad_out)

    out, grads = _at_threads(threads, compiled)
    assert calls["refiner"] == 1 and calls["gru"] == 0
    expected = _gru_reference(gru, torch.tanh(head), torch.zeros_like(prior) if fresh else prior)
    expected_grads = torch.autograd.grad(expected, inputs + weights, grad_out)
    torch.testing.assert_close(out, expected, rtol=1e-12, atol=1e-12)
    for got, want in zip(grads, expected_grads):
        torch.testing.assert_close(got, want, rtol=1e-10, atol=1e-12)
    # NCHW heads take the ConvGRU itself (the torch path)
    torch.testing.assert_close(agent_layers.refine_flow(gru, head, None if fresh else prior), expected)
    assert calls["refiner"] == 1


def test_compiled_gates_pass_gradcheck():
    """Finite differences against the compiled backward passes (float64)."""
    torch.manual_seed(0)
    shape = (2, 4, 3, 5)
    make = lambda c: _cl(torch.randn(shape[0], c, *shape[2:], dtype=torch.float64)).requires_grad_()  # noqa: E731
    for n in (2, 8):
        x_proj, h_proj, hidden = make(6 * n), make(3 * n), make(n)
        h_proj2, hidden2 = make(3 * n), make(n)
        assert torch.autograd.gradcheck(
            lambda a, b, c, d, e: agent_layers._GRUUpdates.apply(n, (0, 3 * n), a, b, c, d, e), (x_proj, h_proj, hidden, h_proj2, hidden2)
        )
        assert torch.autograd.gradcheck(lambda a: agent_layers._GRUUpdates.apply(n, (0,), a[:, : 3 * n].contiguous(memory_format=CHANNELS_LAST), None, None), (x_proj,))
        # GRUs at other column offsets, columns no GRU reads (zero gradient), in any order
        wide = make(7 * n)
        assert torch.autograd.gradcheck(
            lambda a, b, c: agent_layers._GRUUpdates.apply(n, (4 * n,), a, b, c), (wide, h_proj, hidden)
        )
        assert torch.autograd.gradcheck(
            lambda a, b, c, d, e: agent_layers._GRUUpdates.apply(n, (3 * n, 0), a, b, c, d, e), (x_proj, h_proj, hidden, h_proj2, hidden2)
        )
    gate_x, gate_h, fusion = make(4), make(4), make(4)
    assert torch.autograd.gradcheck(agent_layers._OutputGate.apply, (gate_x, gate_h, fusion))
    planar = lambda c: torch.randn(shape[0], c, *shape[2:], dtype=torch.float64).requires_grad_()  # noqa: E731
    assert torch.autograd.gradcheck(agent_layers._PackRefinerInput.apply, (make(2), planar(2)))
    assert torch.autograd.gradcheck(agent_layers._RefinerUpdate.apply, (planar(8), planar(2)))


@pytest.mark.parametrize("name", BUILT_IN)
def test_models_agree_across_memory_layouts(name):
    """Channels-last (CPU default, compiled gates) and NCHW (torch path) give the same flows,
    states and parameter gradients over three windows, at a size that needs padding; the
    flows come back contiguous NCHW either way."""
    models = {}
    for layout in (True, False):
        models[layout] = build(name).double()
        models[layout].channels_last = layout
    results = {}
    for layout, model in models.items():
        state, loss = None, 0
        for seed in range(3):
            flows, state = model(count_images(2, 37, 50, seed=seed).double(), state)
            loss = loss + sum((flow * torch.linspace(0, 1, flow.shape[-1], dtype=torch.float64)).sum() for flow in flows)
        loss.backward()
        assert all(flow.is_contiguous() for flow in flows)
        results[layout] = (flows, state, [p.grad for p in model.parameters()])
    (flows_a, state_a, grads_a), (flows_b, state_b, grads_b) = results[True], results[False]
    for a, b in zip(flows_a, flows_b):
        torch.testing.assert_close(a, b, rtol=1e-10, atol=1e-10)
    assert state_a.keys() == state_b.keys()
    for key in state_a:
        torch.testing.assert_close(state_a[key], state_b[key], rtol=1e-10, atol=1e-10)
    for a, b in zip(grads_a, grads_b):
        assert (a is None) == (b is None)
        if a is not None:
            torch.testing.assert_close(a, b, rtol=1e-8, atol=1e-10)


def test_inference_path_matches_training_path():
    """EV-MGRFlowNet without gradients gives the flows and states of the same model with
    gradients, over three windows."""
    model = build("ev-mgrflownet").double()
    results = []
    for grad in (True, False):
        state, flows_seen = None, []
        with torch.set_grad_enabled(grad):
            for seed in range(3):
                flows, state = model(count_images(2, 37, 50, seed=seed).double(), state)
                flows_seen += [flow.detach() for flow in flows]
        results.append((flows_seen, {k: v.detach() for k, v in state.items()}))
    (flows_a, state_a), (flows_b, state_b) = results
    for a, b in zip(flows_a, flows_b):
        torch.testing.assert_close(a, b, rtol=1e-10, atol=1e-10)
    for key in state_a:
        torch.testing.assert_close(state_a[key], state_b[key], rtol=1e-10, atol=1e-10)


@pytest.mark.cpu_kernels  # the compiled kernels themselves (skipped with EVFLOW_CPU_KERNELS=0)
def test_cpu_default_is_channels_last_with_compiled_gates(monkeypatch):
    calls = _count_gate_kernel_calls(monkeypatch)
    model = build("ev-mgrflownet")
    assert model.channels_last is None
    with torch.no_grad():
        _, state = model(count_images(1, 32, 32), None)
        _, state = model(count_images(1, 32, 32, seed=1), state)
    assert state["encoder1"].is_contiguous(memory_format=CHANNELS_LAST)
    # per window: the ST pair, encoders 2-4; one output gate; four refiners (merged convolution)
    assert calls == {"gru": 2 * 4, "gate": 2, "refiner": 2 * 4}
    model(count_images(1, 32, 32, seed=2), state)  # with gradients: the same passes
    assert calls == {"gru": 3 * 4, "gate": 3, "refiner": 3 * 4}


@pytest.mark.cpu_kernels  # the compiled kernels themselves (skipped with EVFLOW_CPU_KERNELS=0)
def test_bench_agents_parts_rows():
    """``scripts/bench_agents.py --parts`` runs against the current layers and reports every
    piece at both inputs (one timed repetition each)."""
    from evflow_cli.commands import bench_agents as bench

    rows = []
    bench.time_parts(lambda section, name, value, unit: rows.append((name, value, unit)), reps=1)
    names = [name for name, _, _ in rows]
    for input_label in ("256x256 B=1", "128x128 B=8"):
        for piece in ("forward warp", "pair update"):
            assert any(piece in name and input_label in name for name in names), (piece, input_label)
    assert all(value > 0 and unit == "ms" for _, value, unit in rows)


# ---------------------------------------------------------------- published baselines vs their equations

from agents.baselines import SpikingFlowDecoder  # noqa: E402
from agents.layers import ConvUpNearestReflect, HagenaarsConvGRU, ZhuResidualBlock  # noqa: E402
from agents.spiking import XLIFLayer, arctan_surrogate_spike  # noqa: E402


def _conv(x, conv, stride=1, padding=None):
    """conv's weight and bias applied with F.conv2d, 'same' padding unless given."""
    k = conv.weight.shape[-1]
    return F.conv2d(x, conv.weight, conv.bias, stride=stride, padding=k // 2 if padding is None else padding)


def test_hagenaars_convgru_matches_its_equations_and_init():
    """z = sig(Wz*[X,H]), r = sig(Wr*[X,H]), Hhat = tanh(Wh*[X, r.H]) (reset before the
    convolution), H' = (1-z).H + z.Hhat; orthogonal kernels, zero biases; None = zeros."""
    torch.manual_seed(0)
    gru = HagenaarsConvGRU(3, 4).double()
    x, h = torch.randn(2, 3, 5, 6, dtype=torch.float64), torch.randn(2, 4, 5, 6, dtype=torch.float64)
    xh = torch.cat([x, h], 1)
    z = torch.sigmoid(_conv(xh, gru.update_gate))
    r = torch.sigmoid(_conv(xh, gru.reset_gate))
    candidate = torch.tanh(_conv(torch.cat([x, r * h], 1), gru.candidate))
    torch.testing.assert_close(gru(x, h), (1 - z) * h + z * candidate)
    assert torch.equal(gru(x, None), gru(x, torch.zeros_like(h)))
    for conv in (gru.update_gate, gru.reset_gate, gru.candidate):
        w = conv.weight.reshape(4, -1)
        eye = torch.eye(4, dtype=torch.float64)
        torch.testing.assert_close(w @ w.T, eye, rtol=0, atol=1e-6)  # orthonormal rows (drawn in float32)
        assert torch.all(conv.bias == 0)


def test_arctan_surrogate_has_hagenaars_form():
    x = torch.tensor([-0.5, -0.01, 0.0, 0.01, 0.5], requires_grad=True)
    spikes = arctan_surrogate_spike(x, 10.0)
    assert spikes.tolist() == [0.0, 0.0, 0.0, 1.0, 1.0]
    spikes.sum().backward()
    torch.testing.assert_close(x.grad, 1.0 / (1.0 + 10.0 * x.detach() ** 2))  # 1 / (1 + width x^2)


@pytest.mark.parametrize("recurrent", [False, True])
def test_xlif_layer_matches_its_equations_over_two_steps(recurrent):
    """pt_k = b pt + (1-b) avgpool(mean|x|); v_k = a v + (1-a)(W*x [+ R*z]) - sg(z) theta(pt);
    z_k = H(v_k - theta(pt_k)), theta = clamp(t0, 0.01) + clamp(t1, 0) pt, per channel."""
    torch.manual_seed(1)
    layer = XLIFLayer(3, 4, stride=1 if recurrent else 2, recurrent=recurrent).double()
    stride = 1 if recurrent else 2
    assert {n for n, _ in layer.named_buffers()} == {"t0", "t1"}  # thresholds fixed by default
    assert {"leak_v", "leak_pt"} <= {n for n, _ in layer.named_parameters()}
    assert torch.all(layer.t0.float() == 0.01) and torch.all(layer.t1.float() == 1.8)
    bound = (1 / 3) ** 0.5
    assert layer.ff.weight.abs().max() <= bound and layer.ff.bias is None
    state, v, z, pt = None, 0.0, 0.0, 0.0
    for _ in range(2):
        x = (torch.rand(1, 3, 6, 8, dtype=torch.float64) * 4).requires_grad_()
        a, b = torch.sigmoid(layer.leak_v), torch.sigmoid(layer.leak_pt)
        current = _conv(x, layer.ff, stride=stride)
        if recurrent:
            current = current + _conv(torch.as_tensor(z, dtype=torch.float64).expand_as(current), layer.rec)
        trace_in = F.avg_pool2d(x.abs().mean(1, keepdim=True), 3, stride, padding=1)
        pt_new = b * pt + (1 - b) * trace_in
        theta = lambda trace: layer.t0.clamp_min(0.01) + layer.t1.clamp_min(0) * trace  # noqa: E731
        v_new = a * v + (1 - a) * current - torch.as_tensor(z).detach() * theta(pt)
        z_new = (v_new > theta(pt_new)).double()
        out, state = layer(x, state)
        torch.testing.assert_close(state[0], v_new)
        torch.testing.assert_close(state[2], pt_new)
        assert torch.equal(out, z_new) and torch.equal(state[1], z_new)
        v, z, pt = state[0].detach(), state[1].detach(), state[2].detach()
        state = tuple(t.detach() for t in state)
    assert z.sum() > 0  # some neurons fired at step 2
    # the reset's spike is detached: the loss reaches the previous spikes only through R * z
    v0, z0, pt0 = (t.clone().requires_grad_() for t in state)
    _, (v1, _, _) = layer(torch.rand(1, 3, 6, 8, dtype=torch.float64), (v0, z0, pt0))
    v1.sum().backward()
    if recurrent:
        rec_only = F.conv_transpose2d((1 - torch.sigmoid(layer.leak_v)).expand_as(v1), layer.rec.weight, padding=1)
        torch.testing.assert_close(z0.grad, rec_only)
    else:
        assert z0.grad is None or torch.all(z0.grad == 0)
    # clamped thresholds: t0 below 0.01 acts as 0.01, t1 below 0 as 0
    layer.t0.fill_(-1.0)
    layer.t1.fill_(-1.0)
    x = torch.rand(1, 3, 6, 8, dtype=torch.float64)
    out, (v2, _, _) = layer(x, None)
    assert torch.equal(out, (v2 > 0.01).double())


def test_xlif_ev_flownet_is_its_layers_composed():
    """One window of XLIF-EV-FlowNet against the composition written out: encoders ff (stride 2)
    then recurrent XLIF; two spiking residual blocks (spikes + input); decoders bilinear x2 then
    XLIF; 1x1 tanh heads with U(+-0.01) weights and zero biases; flows x flow_scaling."""
    model = build("xlif-ev-flownet", base_width=2, flow_scaling=16.0).double()
    model.channels_last = False
    x = count_images(1, 32, 48).double() * 3
    skips, h = [], x
    for ff, rec in zip(model.encoder_ff, model.encoder_rec):
        h = rec(ff(h, None)[0], None)[0]
        skips.append(h)
    r = h
    for conv1, conv2 in model.residual:
        r = conv2(conv1(r, None)[0], None)[0] + r  # spikes plus the block's input
    decoder = model.decoder
    assert isinstance(decoder, SpikingFlowDecoder)
    d, flows = r, []
    for level in range(4):
        parts = [d, skips[3 - level]] + flows[-1:]
        d = decoder.layers[level](F.interpolate(torch.cat(parts, 1), scale_factor=2, mode="bilinear"), None)[0]
        head = decoder.heads[level]
        assert head.kernel_size == (1, 1) and head.weight.abs().max() <= 0.01 and torch.all(head.bias == 0)
        flows.append(torch.tanh(_conv(d, head)))
    got, state = model(x, None)
    for want, have in zip(flows, got):
        torch.testing.assert_close(have, want * 16.0)
    assert {"encoder1_ff_v", "encoder4_rec_pt", "residual2_conv2_z", "decoder4_v"} <= set(state)


def test_convgru_ev_flownet_is_its_layers_composed():
    """Hagenaars' ConvGRU-EV-FlowNet, one window: F_l = GRU(relu(conv_s2(F_{l-1}))), residual
    blocks relu(conv(relu(conv x)) + x), decoders relu(conv3x3(bilinear_x2([D, F, u]))), 1x1 tanh heads."""
    model = build("convgru-ev-flownet", base_width=2, flow_scaling=16.0).double()
    model.channels_last = False
    x = count_images(1, 32, 48).double()
    skips, h = [], x
    for down, gru in zip(model.downs, model.grus):
        assert isinstance(gru, HagenaarsConvGRU)
        h = gru(F.relu(_conv(h, down.conv, stride=2)), None)
        skips.append(h)
    r = h
    for block in model.residual:
        r = F.relu(_conv(F.relu(_conv(r, block.conv1)), block.conv2) + r)
    d, flows = r, []
    for level in range(4):
        parts = [d, skips[3 - level]] + flows[-1:]
        up = F.interpolate(torch.cat(parts, 1), scale_factor=2, mode="bilinear", align_corners=False)
        d = F.relu(_conv(up, model.decoder.upsamples[level].conv))
        assert model.decoder.heads[level].kernel_size == (1, 1)
        flows.append(torch.tanh(_conv(d, model.decoder.heads[level])))
    got, state = model(x, None)
    for want, have in zip(flows, got):
        torch.testing.assert_close(have, want * 16.0)
    assert set(state) == {f"encoder{l}" for l in range(1, 5)}


def test_zhu_ev_flownet_is_its_layers_composed():
    """Zhu's EV-FlowNet, one window on the 4-channel input: F_l = relu(conv_s2(F_{l-1})),
    residual blocks x + relu(conv(relu(conv x))), decoders relu(conv3x3_valid(reflect_pad_1(
    nearest_x2([D, F, u])))), 1x1 tanh heads; every kernel from a truncated normal of std
    sqrt(1.3 * 0.1 / fan_in), biases 0."""
    torch.manual_seed(0)
    model = make_model("ev-flownet", base_width=2, flow_scaling=16.0).double()
    assert model.in_channels == 4  # counts and latest timestamps per polarity
    model.channels_last = False
    x = torch.cat([count_images(1, 32, 48), torch.rand(1, 2, 32, 48)], 1).double()
    skips, h = [], x
    for down in model.downs:
        h = F.relu(_conv(h, down.conv, stride=2))
        skips.append(h)
    r = h
    for block in model.residual:
        assert isinstance(block, ZhuResidualBlock)
        r = r + F.relu(_conv(F.relu(_conv(r, block.conv1)), block.conv2))
    d, flows = r, []
    for level in range(4):
        parts = torch.cat([d, skips[3 - level]] + flows[-1:], 1)
        up = parts.repeat_interleave(2, dim=2).repeat_interleave(2, dim=3)  # nearest x2
        rows = torch.cat([up[:, :, 1:2], up, up[:, :, -2:-1]], 2)  # reflection: the neighbour, not the edge
        padded = torch.cat([rows[..., 1:2], rows, rows[..., -2:-1]], 3)
        assert isinstance(model.decoder.upsamples[level], ConvUpNearestReflect)
        d = F.relu(_conv(padded, model.decoder.upsamples[level].conv, padding=0))
        flows.append(torch.tanh(_conv(d, model.decoder.heads[level])))
    got, state = model(x, None)
    assert state == {}
    for want, have in zip(flows, got):
        torch.testing.assert_close(have, want * 16.0)
    big = make_model("ev-flownet")  # init statistics on the paper-width layers
    for conv in [m for m in big.modules() if isinstance(m, torch.nn.Conv2d)][:6]:
        w = conv.weight.detach().double()
        std = (1.3 * 0.1 / (w.shape[1] * w.shape[2] * w.shape[3])) ** 0.5
        assert w.abs().max() <= 2 * std + 1e-12 and torch.all(conv.bias == 0)
        assert 0.7 * std < w.std() < 1.0 * std  # a normal truncated at 2 sigma keeps ~0.88 of its std


def test_xlif_options_choose_what_trains():
    """learn_threshold=True makes t0, t1 per-channel parameters (clamped in use, so a gradient
    reaches them only above the clamp); learn_leak=False fixes the leaks as buffers. The network
    passes both options to every spiking layer and rebuilds from its config."""
    layer = XLIFLayer(2, 3, learn_leak=False, learn_threshold=True)
    assert {n for n, _ in layer.named_parameters()} == {"ff.weight", "t0", "t1"}
    assert {n for n, _ in layer.named_buffers()} == {"leak_v", "leak_pt"}
    layer.t0.data.fill_(0.5)  # above the 0.01 clamp: the threshold's gradient reaches t0
    x = torch.rand(1, 2, 6, 6) * 3
    _, state = layer(x, None)
    out, (v, _, _) = layer(x, state)
    v.sum().backward(retain_graph=True)  # the reset uses the previous threshold t0 + t1 pt
    assert layer.t0.grad is not None and layer.t0.grad.abs().sum() > 0 and layer.t1.grad is not None
    model = build("xlif-ev-flownet", learn_threshold=True, learn_leak=False)
    spiking = [m for m in model.modules() if isinstance(m, XLIFLayer)]
    assert len(spiking) == 4 * 2 + 2 * 2 + 4
    assert all(isinstance(m.t0, torch.nn.Parameter) and not isinstance(m.leak_v, torch.nn.Parameter) for m in spiking)
    rebuilt = make_model("xlif-ev-flownet", **model.config)
    rebuilt.load_state_dict(model.state_dict())
    assert rebuilt.config["learn_threshold"] is True
