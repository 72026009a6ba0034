"""agents.wrappers.subwindows: windows cut into sub-windows, flows composed, the network stepped through them."""

import json

import numpy as np
import pytest
import torch

from agents.policy import RecurrentPolicy
from agents.registry import make_model
from agents.wrappers.subwindows import SubWindowPolicy, compose_flows, sub_windows
from envs.env import EventFlowEnv
from envs.events import Events
from envs.windows import Window
from evflow_cli.commands import evaluate as evaluate_script
from tests.recordings import write_translating_recording


def _window(rng, n=500, size=(20, 30), t_start=1_000, t_end=101_001):
    t = np.sort(rng.integers(t_start, t_end, n))
    t[:20] = t_start  # repeated timestamps at the edges too
    events = Events.create(rng.integers(0, size[1], n), rng.integers(0, size[0], n), t, rng.choice([-1, 1], n), size)
    return Window.of(events, t_start, t_end)


@pytest.mark.parametrize("splits", [1, 3, 4])
def test_sub_windows_cut_time_in_equal_parts_and_keep_every_event_once(rng, splits):
    window = _window(rng)
    parts = sub_windows(window, splits)
    assert len(parts) == splits and all(isinstance(part, Window) for part in parts)
    assert parts[0].t_start == window.t_start and parts[-1].t_end == window.t_end
    lengths = [part.t_end - part.t_start for part in parts]
    assert max(lengths) - min(lengths) <= 1
    for a, b in zip(parts[:-1], parts[1:]):
        assert a.t_end == b.t_start
    for part in parts:
        assert np.all((part.events.t >= part.t_start) & (part.events.t < part.t_end))
    for key in ("x", "y", "t", "p"):
        assert np.array_equal(np.concatenate([getattr(part.events, key) for part in parts]), getattr(window.events, key))
    with pytest.raises(ValueError, match="splits"):
        sub_windows(window, 0)


def _bilinear_clamped(field, x, y):
    """field (H, W) read at (x, y) with the position clamped to the frame: the slow way."""
    height, width = field.shape
    x, y = min(max(x, 0.0), width - 1.0), min(max(y, 0.0), height - 1.0)
    x0, y0 = int(np.floor(x)), int(np.floor(y))
    x1, y1 = min(x0 + 1, width - 1), min(y0 + 1, height - 1)
    fx, fy = x - x0, y - y0
    return ((1 - fx) * (1 - fy) * field[y0, x0] + fx * (1 - fy) * field[y0, x1]
            + (1 - fx) * fy * field[y1, x0] + fx * fy * field[y1, x1])


def test_composition_matches_following_each_pixel_point_by_point(rng):
    flows = [rng.normal(0, 3, (2, 7, 9)).astype(np.float32) for _ in range(3)]  # points leave the frame too
    composed = compose_flows(flows)
    for row in range(7):
        for col in range(9):
            x, y = float(col), float(row)
            for flow in flows:
                x, y = x + _bilinear_clamped(flow[0], x, y), y + _bilinear_clamped(flow[1], x, y)
            assert composed[:, row, col] == pytest.approx([x - col, y - row], abs=1e-4)


def test_composition_of_affine_flows_is_exact():
    """Bilinear reading is exact on affine fields, so p -> (I + A) p + b twice is (I + A)^2 p + (I + A) b + b."""
    height, width = 40, 50
    a = np.array([[0.02, -0.05], [0.04, 0.01]])
    b = np.array([1.5, -0.75])
    ys, xs = np.mgrid[0:height, 0:width].astype(np.float64)
    points = np.stack([xs, ys])  # (2, H, W), x first
    flow = (np.einsum("ij,jhw->ihw", a, points) + b[:, None, None]).astype(np.float32)
    step = np.eye(2) + a
    expected = np.einsum("ij,jhw->ihw", step @ step, points) + (step @ b + b)[:, None, None] - points
    inner = (slice(None), slice(3, height - 6), slice(3, width - 6))  # where no point reaches the frame's edge
    assert np.allclose(compose_flows([flow, flow])[inner], expected[inner], atol=1e-3)
    assert np.array_equal(compose_flows([flow]), flow)
    uniform = [np.full((2, 5, 6), v, np.float32) for v in (0.5, -2.0, 1.25)]
    assert np.allclose(compose_flows(uniform), -0.25)


def _net(seed=0):
    torch.manual_seed(seed)
    return RecurrentPolicy(make_model("ev-mgrflownet", width="cpu", in_channels=5).eval(), input_key="voxel_grid", voxel_bins=5)


def _env_windows(path, count):
    env = EventFlowEnv(str(path), window_size=2, observations=("count_image", "voxel_grid", "count_time_image"))
    obs, info = env.reset(options={"sequence": 0})
    out = []
    for _ in range(count):
        out.append((obs, info["window"]))
        obs, _, _, _, info = env.step(np.zeros((2, env.height, env.width), np.float32))
    env.close()
    return out


def test_sub_window_inputs_are_the_envs_and_one_split_is_the_network_itself(tmp_path, rng):
    path = write_translating_recording(tmp_path / "rec.h5", rng, sensor_size=(32, 48))
    windows = _env_windows(path, 3)
    wrapped = SubWindowPolicy(_net(), splits=1)
    plain = _net()
    for obs, window in windows:
        for key in ("count_image", "voxel_grid", "count_time_image"):
            wrapped.input_key = key
            assert np.array_equal(wrapped.observation(window, (32, 48))[key], obs[key])
        wrapped.input_key = "voxel_grid"
        assert np.array_equal(wrapped.act(obs, window), plain.act(obs))


def test_the_network_steps_through_the_sub_windows_with_its_state(tmp_path, rng):
    path = write_translating_recording(tmp_path / "rec.h5", rng, sensor_size=(32, 48))
    wrapped, by_hand = SubWindowPolicy(_net(), splits=2), _net()
    for obs, window in _env_windows(path, 3):
        flows = [by_hand.act(wrapped.observation(part, (32, 48))) for part in sub_windows(window, 2)]
        assert np.allclose(wrapped.act(obs, window), compose_flows(flows), atol=1e-6)
    wrapped.reset()
    assert wrapped.policy.state is None


def test_evaluate_adds_a_split_row_per_model_and_checks_the_option(tmp_path, rng):
    path = write_translating_recording(tmp_path / "rec.h5", rng, sensor_size=(32, 48))
    out = tmp_path / "ev"
    evaluate_script.main(["--model", "unet-feedforward", "--width", "4", "--split", "dt", "--dt", "1", "2",
                          "--data", str(path), "--out", str(out), "--no-progress", "--pictures", "0",
                          "--max-windows", "3"])
    results = json.loads((out / "results.json").read_text())
    assert "unet-feedforward + split dt" in results["baselines"] and set(results["overall"]) >= {"dt1", "dt2"}

    def aee(table):
        return {line.split("|")[1].strip(): line.split("|")[2] for line in table.splitlines() if line.startswith("| unet")}

    dt1, dt2 = (out / "table.md").read_text().split("**windows of")[1:]
    # stepped once per window at dt = 1 a model gives exactly its own row; at dt = 2 twice: another flow
    assert aee(dt1)["unet-feedforward"] == aee(dt1)["unet-feedforward + split dt"]
    assert aee(dt2)["unet-feedforward"] != aee(dt2)["unet-feedforward + split dt"]
    with pytest.raises(SystemExit, match="--split"):
        evaluate_script.main(["--zero", "--split", "0", "--data", str(path), "--out", str(out)])


def test_the_default_steps_once_per_ground_truth_interval():
    from agents.pretrained import default_steps

    stepped, one_pass = {"split": "dt"}, {"mode": "one pass per window"}
    assert [default_steps("frames", n, choice=stepped) for n in (None, 1, 4)] == [1, 1, 4]
    assert default_steps("time", 133_332, 33_333, choice=stepped) == 4  # 4 intervals of 33.3 ms, rounded
    assert default_steps("time", 10_000, 33_333, choice=stepped) == 1  # never below one step
    assert default_steps("count", 15_000, choice=stepped) == 1
    assert default_steps("frames", 4, choice=one_pass) == 1


def test_evaluate_runs_the_default_without_a_name_in_its_mode(tmp_path, rng, monkeypatch):
    """--pretrained alone: the default model in the mode default.json records (one step per
    ground-truth interval), its row the same flow as --pretrained NAME --split dt; a mode given on
    the command line (--split, --mirror) is the user's instead."""
    import agents.pretrained as pretrained

    path = write_translating_recording(tmp_path / "rec.h5", rng, sensor_size=(32, 48))
    monkeypatch.setattr(pretrained, "default_choice", lambda directory=None: {"model": pretrained.DEFAULT_PRETRAINED,
                                                                             "split": "dt"})
    name = pretrained.DEFAULT_PRETRAINED
    common = ["--dt", "2", "--data", str(path), "--no-progress", "--pictures", "0", "--max-windows", "3"]
    evaluate_script.main(["--pretrained", *common, "--out", str(tmp_path / "default")])
    evaluate_script.main(["--pretrained", name, "--split", "dt", *common, "--out", str(tmp_path / "named")])
    default = json.loads((tmp_path / "default" / "results.json").read_text())
    named = json.loads((tmp_path / "named" / "results.json").read_text())
    assert default["method"] == f"{name} (pretrained) + split dt (the default's mode)"
    assert default["overall"]["dt2"]["aee"] == named["baselines"][f"{name} (pretrained) + split dt"]["overall"]["dt2"]["aee"]
    assert default["overall"]["dt2"]["aee"] != named["overall"]["dt2"]["aee"]  # the one pass differs at dt = 2
    evaluate_script.main(["--pretrained", "--mirror", "2", *common, "--out", str(tmp_path / "mirror")])
    mirrored = json.loads((tmp_path / "mirror" / "results.json").read_text())
    assert mirrored["method"] == f"{name} (pretrained)"
    with pytest.raises(SystemExit, match="--split dt steps once per ground-truth interval"):
        evaluate_script.main(["--pretrained", "--split", "dt", "--window", "time", "--data", str(path),
                              "--out", str(tmp_path / "time")])
