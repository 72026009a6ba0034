"""Every supported recording format goes straight into the env and the evaluation script."""

import json

import gymnasium
import numpy as np
import pytest

import envs  # noqa: F401  (registers EventFlow-v0)
from evflow_cli.commands import evaluate as evaluate_script  # noqa: E402
from tests.test_readers import _stream, write_dsec, write_ecd, write_hagenaars, write_mvsec


def _files(tmp_path, rng):
    x, y, t, p = _stream(rng, 6000, (20, 30), 120_000)
    t = t - t[0]
    big = _stream(rng, 6000, (260, 346), 120_000)
    gt_t = np.arange(4) * 50_000
    flow = np.ones((4, 260, 346))
    return {
        "mvsec": write_mvsec(tmp_path, "indoor_flying1", *big[:2], big[2] - big[2][0], big[3], gt=(gt_t, 2 * flow, -flow)),
        "hagenaars": write_hagenaars(tmp_path / "hag.h5", x, y, t, p),
        "dsec": write_dsec(tmp_path / "dsec", x, y, t, p),
        "ecd-text": write_ecd(tmp_path / "ecd", x, y, t, p),
    }


@pytest.mark.parametrize("fmt", ["mvsec", "hagenaars", "dsec", "ecd-text"])
def test_env_and_evaluate_take_every_format(tmp_path, fmt):
    path = _files(tmp_path, np.random.default_rng(0))[fmt]
    if fmt == "ecd-text":
        kwargs = {"data_options": {"sensor_size": (20, 30)}}
    else:
        kwargs = {}
    env = gymnasium.make("EventFlow-v0", data=str(path), window="time", window_size=10_000, **kwargs)
    obs, info = env.reset(seed=0)
    assert obs["count_image"].shape[0] == 2 and len(info["window"].events.t) > 0
    _, reward, *_ = env.step(np.zeros(env.action_space.shape, np.float32))
    assert np.isfinite(reward) and reward < 0
    env.close()
    if fmt != "ecd-text":  # (the text reader needs its sensor size given)
        evaluate_script.main(["--zero", "--data", str(path), "--out", str(tmp_path / "ev"), "--no-progress",
                              "--pictures", "0", "--max-windows", "3"])
        results = json.loads((tmp_path / "ev" / "results.json").read_text())
        assert results["overall"]["fwl"] == pytest.approx(1.0)


def test_mvsec_crop_and_frames_windows_through_the_env(tmp_path):
    path = _files(tmp_path, np.random.default_rng(1))["mvsec"]
    env = gymnasium.make("EventFlow-v0", data=str(path), format="mvsec", data_options={"crop": "center256", "grid": "gt"})
    obs, info = env.reset(seed=0)
    assert obs["count_image"].shape == (2, 256, 256)
    np.testing.assert_allclose(info["flow_gt"][0][info["flow_gt_valid"]], 2.0)
