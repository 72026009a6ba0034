"""Propose and finish: the default's mode (agents/wrappers/refine.py FinishedPolicy, its
``finish`` in agents/weights/default.json) in the wrapper, evaluate and predict."""

from __future__ import annotations

import json

import h5py
import numpy as np
import pytest

import agents.pretrained as pretrained
from agents.cmax import FRAME_US
from agents.wrappers.refine import Finish, FinishedPolicy, RefinedPolicy
from envs.windows import Window
from evflow_cli.commands import evaluate as evaluate_script
from evflow_cli.commands import predict as predict_command
from tests.recordings import translating_dots, write_translating_recording

FINISH = [{"solver": "fine", "steps": 2, "up_to_frames": 1.5}, {"solver": "cmax", "steps": 5, "max_events": 300}]


class _Constant:
    input_key, voxel_bins, device = "count_image", 5, "cpu"

    def reset(self, mask=None):
        pass

    def act(self, obs, window=None):
        return np.full((2, *obs[self.input_key].shape[-2:]), 0.5, np.float32)


def _window(rng, frames: float):
    events, (t0, t1) = translating_dots(rng, sensor_size=(21, 31), velocity=(120.0, -90.0),
                                        duration_us=int(frames * FRAME_US), num_dots=60, events_per_s=100_000)
    return Window.of(events, t0, t1)


def test_the_window_length_picks_the_finish_and_each_is_the_plain_refinement(rng):
    obs = {"count_image": np.zeros((2, 21, 31), np.float32)}
    policy = FinishedPolicy(_Constant(), FINISH)
    short, long = _window(rng, 1.0), _window(rng, 4.0)
    assert (policy.finish_for(short), policy.finish_for(long)) == (0, 1)
    for window, (solver, steps, events) in ((short, ("fine", 2, None)), (long, ("cmax", 5, 300))):
        alone = RefinedPolicy(_Constant(), solver=solver, steps=steps, max_events=events).act(obs, window)
        np.testing.assert_allclose(policy.act(obs, window), alone, atol=1e-6)
    assert [f.label() for f in policy.finishes] == ["fine:2", "cmax:5/300"]
    only_short = FinishedPolicy(_Constant(), FINISH[:1])  # no finish fits: the proposal unchanged
    assert only_short.finish_for(long) is None and np.all(only_short.act(obs, long) == 0.5)
    with pytest.raises(ValueError, match="unknown keys"):
        FinishedPolicy(_Constant(), [{"solver": "fine", "steps": 2, "upto": 1}])
    with pytest.raises(ValueError, match="solver must be one of"):
        FinishedPolicy(_Constant(), [{"solver": "slow", "steps": 2}])


def test_the_shipped_default_records_its_finish_and_how_it_was_chosen():
    choice = pretrained.default_choice()
    finishes = [Finish.from_dict(f) for f in pretrained.default_finish()]
    assert finishes and all(f.solver in RefinedPolicy.SOLVERS and f.steps > 0 for f in finishes)
    assert finishes[-1].up_to_frames is None  # every window length gets a finish
    assert "finish" in choice["mode"] and "devval" in choice["chosen_on"]


def test_evaluate_runs_the_default_finished_with_the_network_alone_beside_it(tmp_path, rng, monkeypatch):
    path = write_translating_recording(tmp_path / "rec.h5", rng, sensor_size=(32, 48))
    name = pretrained.DEFAULT_PRETRAINED
    monkeypatch.setattr(pretrained, "default_choice", lambda directory=None: {"model": name, "finish": FINISH[:1]})
    common = ["--dt", "1", "--data", str(path), "--no-progress", "--pictures", "0", "--max-windows", "3"]
    evaluate_script.main(["--pretrained", *common, "--out", str(tmp_path / "default")])
    evaluate_script.main(["--pretrained", name, "--refine", "2", *common, "--out", str(tmp_path / "named")])
    default = json.loads((tmp_path / "default" / "results.json").read_text())
    named = json.loads((tmp_path / "named" / "results.json").read_text())
    assert default["method"] == f"{name} (pretrained) + finish fine:2 (the default's mode)"
    refined = named["baselines"][f"{name} (pretrained) + refine 2"]["overall"]["dt1"]["aee"]
    assert default["overall"]["dt1"]["aee"] == pytest.approx(refined, rel=1e-6)
    alone = default["baselines"][f"{name} (pretrained), network alone"]["overall"]["dt1"]["aee"]
    assert alone == pytest.approx(named["overall"]["dt1"]["aee"], rel=1e-6) and alone != default["overall"]["dt1"]["aee"]


def test_predict_finishes_the_default_and_says_so(tmp_path, monkeypatch):
    name = pretrained.DEFAULT_PRETRAINED
    monkeypatch.setattr(pretrained, "default_choice", lambda directory=None: {
        "model": name, "mode": "propose and finish", "chosen_on": "devval", "finish": FINISH})
    common = ["synthetic-mini", "--end", "0.15", "--no-video", "--no-progress"]

    def run(label: str, *extra: str):
        out, summary = tmp_path / f"{label}.h5", tmp_path / f"{label}.json"
        assert predict_command.main([*common, *extra, "--out", str(out), "--json", str(summary)]) == 0
        with h5py.File(out, "r") as f:
            return np.asarray(f["flow"]), json.loads(summary.read_text())["model"]

    finished, provenance = run("default")
    assert provenance["default"]["finish"] == ["fine:2 up to 1.5 frames", "cmax:5/300"]
    alone, provenance = run("alone", "--no-finish")
    assert "finish" not in provenance["default"] and not np.allclose(finished, alone)
    named, _ = run("named", "--model", name)
    np.testing.assert_array_equal(named, alone)  # a model named explicitly runs as asked: no finish


def _tiny_network():
    import torch

    from agents.policy import RecurrentPolicy
    from agents.registry import make_model

    torch.manual_seed(0)
    return RecurrentPolicy(make_model("ev-mgrflownet", base_width=4).eval(), device="cpu")


def test_a_coarse_finish_finishes_the_network_on_the_coarser_grid(rng):
    from agents.wrappers.coarse import CoarsePolicy

    obs = {"count_image": np.zeros((2, 21, 31), np.float32)}
    long = _window(rng, 4.0)
    finish = Finish("cmax", 5, 300, None, coarse=2)
    assert finish.label() == "coarse2+cmax:5/300" and Finish.from_dict({**FINISH[1], "coarse": 2}) == finish
    policy = FinishedPolicy(_tiny_network(), [finish])
    reference = RefinedPolicy(CoarsePolicy(_tiny_network(), 2), solver="cmax", steps=5, max_events=300)
    np.testing.assert_allclose(policy.act(obs, long), reference.act(obs, long), atol=1e-6)
    with pytest.raises(ValueError, match="coarse must be an integer"):
        Finish("cmax", 5, coarse=0)


def test_each_grid_keeps_its_own_recurrent_state_when_window_lengths_change(rng):
    """Windows of one length, then of another, then of the first: the sensor-grid proposals are
    those of a network that saw only the short windows, the coarse ones those of a coarse
    network that saw only the long ones (no state crosses between grids)."""
    from agents.wrappers.coarse import CoarsePolicy

    image = {"count_image": np.zeros((2, 21, 31), np.float32)}
    short, long = [_window(rng, 1.0) for _ in range(3)], [_window(rng, 4.0) for _ in range(2)]
    steps = [0, 1]  # no finish: the proposals themselves
    policy = FinishedPolicy(_tiny_network(), [Finish("fine", 0, None, 1.5), Finish("cmax", 0, coarse=2)])
    from envs.representations import image_input

    def obs(w):
        return {"count_image": image_input("count_image", w.events, w.t_start, w.t_end, (21, 31), 5)}

    order = [short[0], long[0], short[1], long[1], short[2]]
    flows = [policy.act(obs(w), w) for w in order]
    fine, coarse = _tiny_network(), CoarsePolicy(_tiny_network(), 2)
    expected_short = [fine.act(obs(w), w) for w in short]
    expected_long = [coarse.act(image, w) for w in long]
    for got, want in zip([flows[0], flows[2], flows[4]], expected_short):
        np.testing.assert_allclose(got, want, atol=1e-6)
    for got, want in zip([flows[1], flows[3]], expected_long):
        np.testing.assert_allclose(got, want, atol=1e-6)
    assert steps and not np.allclose(flows[0], flows[2])  # the state carried: a later window differs


def test_predict_coarse_runs_the_network_on_the_coarser_grid_and_records_it(tmp_path, monkeypatch):
    from agents.policy import RecurrentPolicy
    from agents.wrappers.coarse import CoarsePolicy
    from evflow_cli.predict import predict

    name = pretrained.DEFAULT_PRETRAINED
    monkeypatch.setattr(pretrained, "default_choice", lambda directory=None: {
        "model": name, "mode": "propose and finish", "chosen_on": "devval", "finish": FINISH})
    common = ["synthetic-mini", "--end", "0.15", "--no-video", "--no-progress", "--coarse", "2"]
    summary = tmp_path / "coarse.json"
    assert predict_command.main([*common, "--out", str(tmp_path / "c.h5"), "--json", str(summary)]) == 0
    provenance = json.loads(summary.read_text())["model"]
    assert provenance["coarse"] == 2
    assert provenance["default"]["finish"] == ["coarse2+fine:2 up to 1.5 frames", "coarse2+cmax:5/300"]
    with pytest.raises(ValueError, match="--coarse takes a factor from 1 to 16"):
        predict_command.main([*common[:-1], "17", "--out", str(tmp_path / "never.h5")])
    assert not (tmp_path / "never.h5").exists()
    assert predict_command.main([*common, "--no-finish", "--out", str(tmp_path / "alone.h5")]) == 0
    reference = predict(CoarsePolicy(RecurrentPolicy.from_pretrained(name), 2), "synthetic-mini", tmp_path / "ref.h5",
                        end_s=0.15, progress=False)
    with h5py.File(tmp_path / "alone.h5", "r") as a, h5py.File(reference.path, "r") as b:
        np.testing.assert_array_equal(np.asarray(a["flow"]), np.asarray(b["flow"]))
        assert np.abs(np.asarray(a["flow"])).max() > 0
