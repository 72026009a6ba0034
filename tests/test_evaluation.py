"""agents.evaluation and scripts/evaluate.py: every recording whole at its own size, the
windowing of recordings without ground truth, the contrast-maximisation row and refinement."""

import json

import gymnasium
import numpy as np
import pytest
import torch

import envs  # noqa: F401  (registers EventFlow-v0)
from agents.cmax import CMaxSettings, ContrastMaximisationPolicy
from agents.evaluation import evaluate, results_table
from agents.policy import RecurrentPolicy
from agents.registry import make_model
from agents.wrappers import RefinedPolicy
from envs.env import EventFlowEnv
from envs.events import Events
from envs.windows import Window
from evflow_cli.commands import evaluate as evaluate_script  # noqa: E402
from losses import EventBatch, contrast_maximisation_flow, hmc_loss, window_loss
from tests.recordings import translating_dots, write_translating_recording
from tests.test_readers import _stream, write_hagenaars


def _policy(seed=0):
    torch.manual_seed(seed)
    return RecurrentPolicy(make_model("unet-feedforward", base_width=4).eval())


def _rows(results):
    return [r.as_dict() for r in results]


def test_recordings_of_different_sizes_score_as_each_alone(tmp_path, rng):
    small = write_translating_recording(tmp_path / "small.h5", rng, sensor_size=(32, 32))
    large = write_translating_recording(tmp_path / "large.h5", rng, sensor_size=(64, 48), velocity=(-90.0, 300.0))
    policy = _policy()
    together = evaluate(policy, [str(small), str(large)], progress=False, max_windows=4)
    alone = evaluate(policy, str(small), progress=False, max_windows=4) + evaluate(policy, str(large), progress=False,
                                                                                  max_windows=4)
    assert [r.size for r in together] == [(32, 32), (64, 48)]  # each whole, nothing cropped
    for a, b in zip(_rows(together), _rows(alone)):
        assert a.pop("size") == b.pop("size") and a.pop("windowing") == b.pop("windowing")
        a.pop("ms"), b.pop("ms")
        assert a == pytest.approx(b, nan_ok=True)


def test_a_size_off_the_networks_stride_is_evaluated_whole(tmp_path, rng):
    path = write_translating_recording(tmp_path / "odd.h5", rng, sensor_size=(37, 45))
    (result,) = evaluate(_policy(), str(path), progress=False, max_windows=3, pictures_dir=tmp_path / "pics",
                         pictures_per_sequence=1, animation_windows=3)
    assert result.size == (37, 45) and result.windows == 3 and np.isfinite(result.mean("aee"))
    assert (tmp_path / "pics" / "odd_w000.png").exists() and (tmp_path / "pics" / "odd.gif").exists()


def test_a_recording_without_ground_truth_gives_one_table_and_runs_in_the_env(tmp_path, rng):
    x, y, t, p = _stream(rng, 4_000, (20, 30), 200_000)
    path = write_hagenaars(tmp_path / "nogt.h5", x, y, t - t[0], p)
    env = gymnasium.make("EventFlow-v0", data=str(path))  # default window mode
    obs, info = env.reset(seed=0)
    assert info["windowing"] == "time" and info["window"].t_end - info["window"].t_start == 33_333
    env.close()
    evaluate_script.main(["--zero", "--data", str(path), "--out", str(tmp_path / "ev"), "--no-progress",
                          "--pictures", "0"])
    table = (tmp_path / "ev" / "table.md").read_text()
    assert table.count("| method |") == 1 and "fixed 33333 us intervals" in table
    results = json.loads((tmp_path / "ev" / "results.json").read_text())
    n = results["overall"]["dt1"]["windows"]
    assert list(results["overall"]) == ["dt1", "fwl", "rsat"] and n == -(-(int(t[-1]) - int(t[0]) + 1) // 33_333)
    evaluate_script.main(["--zero", "--data", str(path), "--out", str(tmp_path / "ev4"), "--no-progress",
                          "--pictures", "0", "--dt", "4"])  # asked for: 4 intervals per window
    results = json.loads((tmp_path / "ev4" / "results.json").read_text())
    assert results["overall"]["dt4"]["windows"] == n // 4


def _translation_window(rng, velocity=(150.0, -60.0), size=(48, 64)):
    events, (t0, t1) = translating_dots(rng, sensor_size=size, velocity=velocity, duration_us=33_333,
                                        num_dots=150, events_per_s=300_000)
    window = Window.of(events, t0, t1)
    truth = np.array(velocity) * (t1 - t0) / 1e6
    return window, truth


def test_cmax_finds_an_analytic_translation(rng):
    window, truth = _translation_window(rng)
    flow = ContrastMaximisationPolicy().act({"count_image": np.zeros((2, 48, 64))}, window)
    mean = flow.reshape(2, -1).mean(1)
    assert np.abs(mean - truth).max() < 0.6, (mean, truth)  # 5 px and 2 px of motion, found within 0.6 px


class _Constant:
    """A 'network' that always predicts the same flow."""

    input_key, voxel_bins, device = "count_image", 5, "cpu"

    def __init__(self, flow):
        self.flow = flow

    def reset(self, mask=None):
        pass

    def act(self, obs):
        return self.flow.copy()


@pytest.mark.parametrize("solver, steps", [("fine", 60), ("cmax", 100)])
def test_refinement_lowers_the_loss_honours_zero_steps_and_converges(rng, solver, steps):
    window, truth = _translation_window(rng)
    start = np.zeros((2, 48, 64), np.float32)
    start[0], start[1] = truth[0] * 0.5, truth[1] * 0.5  # a network half way there
    obs = {"count_image": np.zeros((2, 48, 64), np.float32)}
    assert np.array_equal(RefinedPolicy(_Constant(start), steps=0, solver=solver).act(obs, window), start)
    policy = RefinedPolicy(_Constant(start), steps=steps, solver=solver)
    assert policy.steps == steps
    refined = policy.act(obs, window)
    batch = EventBatch.from_windows([window])

    def loss(f):
        return float(hmc_loss(torch.from_numpy(f)[None], batch, flow_scaling=64).loss)

    assert loss(refined) < loss(start)
    assert np.abs(refined.reshape(2, -1).mean(1) - truth).max() < 0.5 < np.abs(start[:, 0, 0] - truth).max()


def test_a_strong_prior_holds_the_refinement_to_the_networks_flow(rng):
    window, truth = _translation_window(rng)
    start = np.zeros((2, 48, 64), np.float32)
    start[0], start[1] = truth[0] * 0.5, truth[1] * 0.5
    obs = {"count_image": np.zeros((2, 48, 64), np.float32)}
    moved = {w: np.abs(RefinedPolicy(_Constant(start), steps=60, prior_weight=w).act(obs, window)
                       - start).mean() for w in (0.0, 1e4)}
    assert moved[1e4] < 0.05 * moved[0.0] and moved[0.0] > 0.5  # held near the start, and free without
    for bad in (-1.0, [1.0, 2.0], float("nan")):  # one window: one weight, finite, >= 0
        with pytest.raises(ValueError, match="prior_weight must be one finite weight >= 0"):
            contrast_maximisation_flow(EventBatch.from_windows([window]), 48, 64, prior_weight=bad)


def test_the_acceptance_gate_keeps_the_refinement_only_where_the_loss_drops_enough(rng):
    """accept = a: the refined flow where the env's loss (window_loss: L_HMC with the border rule,
    flow scaling max(H, W)) falls by at least a of the network's, else the network's flow exactly;
    accept = 0 keeps only refinements that do not raise it. Checked against the rule computed
    here, from a start half way to a translation (a large drop), from the translation itself (a
    small one: the solve still finds a slightly lower loss) and from zero (the local solve raises it)."""
    window, truth = _translation_window(rng)
    obs = {"count_image": np.zeros((2, 48, 64), np.float32)}
    batch = EventBatch.from_windows([window])

    def loss(f):
        return float(window_loss(torch.from_numpy(f)[None], batch, flow_scaling=64).loss)

    for fraction, expect_refined in ((0.5, True), (1.0, False), (0.0, False)):
        start = np.zeros((2, 48, 64), np.float32)
        start[0], start[1] = truth[0] * fraction, truth[1] * fraction
        refined = RefinedPolicy(_Constant(start), steps=60).act(obs, window)
        drop = 1 - loss(refined) / loss(start)
        gated = RefinedPolicy(_Constant(start), steps=60, accept=0.15)
        out = gated.act(obs, window)
        assert (drop >= 0.15) == expect_refined, drop
        assert np.array_equal(out, refined if expect_refined else start)
        assert (gated.accepted, gated.refined) == (int(expect_refined), 1)
        kept = RefinedPolicy(_Constant(start), steps=60, accept=0.0).act(obs, window)
        assert np.array_equal(kept, refined if drop >= 0 else start)
    with pytest.raises(ValueError, match=r"accept must be a fraction in \[0, 1\), got 1.5"):
        RefinedPolicy(_Constant(start), accept=1.5)


def test_an_unknown_refinement_solver_is_refused():
    with pytest.raises(ValueError, match=r"solver must be one of \('fine', 'cmax', 'mid'\), got 'coarse'"):
        RefinedPolicy(_Constant(np.zeros((2, 4, 4), np.float32)), solver="coarse")


def test_table_counts_sequences_below_zero_flow(tmp_path, rng):
    path = write_translating_recording(tmp_path / "rec.h5", rng, sensor_size=(32, 32))
    named = {"cmax": evaluate(ContrastMaximisationPolicy(CMaxSettings(steps=(10, 10, 10))), str(path),
                              progress=False, max_windows=2),
             "zero flow": evaluate(None, str(path), progress=False, max_windows=2)}
    table = results_table(named)
    assert "| zero flow |" in table and "0/1" in table and "ms/win" in table


def test_the_l_hmc_column_is_the_envs_reward(tmp_path, rng):
    """The evaluation's L_HMC (and its "seq. L_HMC < zero" count) is the mean of -reward from
    stepping the env with the same flow, border rule included (not the plain L_HMC)."""
    path = write_translating_recording(tmp_path / "tiny.h5", rng, sensor_size=(32, 32), duration_us=150_000)
    flow = np.zeros((2, 32, 32), np.float32)
    flow[0], flow[1] = 9.0, -4.0  # pushes some events out of the frame: the border rule charges it
    (result,) = evaluate(_Constant(flow), str(path), progress=False)
    env = EventFlowEnv(str(path))
    _, info = env.reset(options={"sequence": 0})
    losses, plain, zero, truncated = [], [], [], False
    while not truncated:
        window = info["window"]
        _, reward, _, truncated, info = env.step(flow)
        if len(window.events):
            losses.append(-reward)
            batch = window.batch()
            plain.append(float(hmc_loss(torch.from_numpy(flow)[None], batch, flow_scaling=32).loss))
            zero.append(float(hmc_loss(torch.zeros(1, 2, 32, 32), batch, flow_scaling=32).loss))
    assert result.windows == len(losses) == 5 and result.counts["hmc"] == len(losses)
    assert result.mean("hmc") == pytest.approx(np.mean(losses), rel=1e-6)
    assert result.mean("hmc_zero") == pytest.approx(np.mean(zero), rel=1e-6)
    assert result.mean("hmc") > np.mean(plain) * 1.01  # the border rule is in it
    table = results_table({"flow": [result]})
    assert f"| {np.mean(losses):.4f} | {np.mean(zero):.4f} | {int(np.mean(losses) < np.mean(zero))}/1 |" in table


def test_env_refuses_mixed_sizes_but_evaluation_takes_them(tmp_path, rng):
    a = write_translating_recording(tmp_path / "a.h5", rng, sensor_size=(32, 32))
    b = write_translating_recording(tmp_path / "b.h5", rng, sensor_size=(40, 32))
    with pytest.raises(ValueError, match=r"'a' 32x32.*'b' 40x32"):
        env = EventFlowEnv([str(a), str(b)])
        env.reset(options={"sequence": 1})


def test_the_time_per_window_leaves_out_each_sequences_warm_up_window(tmp_path, rng):
    import time

    class SlowFirst:  # a policy whose first window of a sequence is slow (as kernel compilation is)
        def reset(self):
            self.first = True

        def act(self, obs, window=None):
            if self.first:
                time.sleep(0.3)
                self.first = False
            return np.zeros((2, 32, 32), np.float32)

    path = write_translating_recording(tmp_path / "dots.h5", rng, sensor_size=(32, 32))
    (result,) = evaluate(SlowFirst(), str(path), progress=False, max_windows=4)
    assert result.windows == 4 and result.counts["ms"] == 3 and result.mean("ms") < 150


def _noise_window(rng, n=600, size=(48, 64)):
    """A still scene seen only through background activity: uniform events, true flow zero."""
    t = np.sort(rng.integers(0, 33_333, n))
    events = Events(rng.integers(0, size[1], n).astype(np.float32), rng.integers(0, size[0], n).astype(np.float32),
                    t.astype(np.int64), rng.choice(np.array([-1, 1], np.int8), n), size)
    return Window.of(events, 0, 33_333)


def test_the_evidence_prior_keeps_a_sparse_still_window_still_and_finds_a_dense_translation(rng):
    """CMaxSettings.evidence_prior: the plain solve invents motion on 600 noise events (it lowers
    the loss by collapsing them); held toward zero with weight C / 600 it stays many times nearer
    zero. On the 10,000-event translation the same C (weight 3) still finds the motion."""
    obs = {"count_image": np.zeros((2, 48, 64))}
    noise = _noise_window(rng)
    plain = np.abs(ContrastMaximisationPolicy().act(obs, noise)).mean()
    held = np.abs(ContrastMaximisationPolicy(CMaxSettings(evidence_prior=30_000.0)).act(obs, noise)).mean()
    assert plain > 0.3 and held < 0.2 * plain, (plain, held)
    window, truth = _translation_window(rng)
    flow = ContrastMaximisationPolicy(CMaxSettings(evidence_prior=30_000.0)).act(obs, window)
    assert np.abs(flow.reshape(2, -1).mean(1) - truth).max() < 0.6


def test_one_prior_weight_per_window_solves_each_window_as_alone(rng):
    """A batch with prior weights (0, 10^4) gives each window the flow of its own solve with its
    own weight (the windows do not share a weight)."""
    window, _ = _translation_window(rng)
    kwargs = dict(grids=(2, 4), steps=10, lr=0.3)
    together = contrast_maximisation_flow(EventBatch.from_windows([window, window]), 48, 64, prior_weight=[0.0, 1e4],
                                          **kwargs)
    for i, weight in enumerate((0.0, 1e4)):
        alone = contrast_maximisation_flow(EventBatch.from_windows([window]), 48, 64, prior_weight=weight, **kwargs)
        assert torch.allclose(together[i], alone[0], atol=1e-4)
    assert together[1].abs().mean() < 0.2 * together[0].abs().mean()  # the weight acts
