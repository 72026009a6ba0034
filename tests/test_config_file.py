"""--config: a run's saved config.json starts a new run with the same config; a TOML file sets
evaluate's options as the command line would; a misspelt key is an error naming it; the run
records the code that made it."""

from __future__ import annotations

import json

import pytest

from agents.options import expand_config
from evflow_cli.commands import evaluate as evaluate_script
from evflow_cli.commands import train as train_script
from tests.recordings import write_translating_recording


def _config(path):
    values = json.loads(path.read_text())
    return {k: v for k, v in values.items() if not k.startswith("_")}, values.get("_run")


def test_a_saved_config_reproduces_the_run_config(tmp_path):
    first = tmp_path / "first"
    argv = ["--model", "ev-flownet", "--width", "4", "--data", "synthetic-mini", "--crop", "32", "32", "--random-crop",
            "--window-size", "1", "2", "--num-envs", "2", "--unroll", "2", "--steps", "1", "--lr", "3e-4",
            "--model-kwarg", "flow_scaling=16", "--no-flips", "--loss-scales", "finest", "--no-progress"]
    assert train_script.main([*argv, "--out", str(first)]) in (0, None)
    assert train_script.main(["--config", str(first / "config.json"), "--out", str(tmp_path / "second"),
                              "--no-progress"]) in (0, None)
    (a, run_a), (b, _) = _config(first / "config.json"), _config(tmp_path / "second" / "config.json")
    assert a == b and a["model_kwargs"] == {"flow_scaling": 16} and a["window_size"] == [1, 2]
    assert run_a["code"]["git_commit"] and len(run_a["code"]["git_commit"]) == 40
    # an option given beside the file wins
    parser = train_script.build_parser()
    args = parser.parse_args(expand_config(parser, ["--config", str(first / "config.json"), "--lr", "1e-3"]))
    assert args.lr == 1e-3 and args.model == "ev-flownet"


def test_a_toml_config_is_the_command_line(tmp_path, rng):
    path = write_translating_recording(tmp_path / "rec.h5", rng, sensor_size=(32, 48))
    (tmp_path / "eval.toml").write_text(f'pretrained = []\nzero = true\ndata = ["{path}"]\nwindow-size = [1]\n'
                                        'max_windows = 2\npictures = 0\nno_progress = true\n')
    evaluate_script.main(["--config", str(tmp_path / "eval.toml"), "--out", str(tmp_path / "a")])
    evaluate_script.main(["--pretrained", "--zero", "--data", str(path), "--window-size", "1", "--max-windows", "2",
                          "--pictures", "0", "--no-progress", "--out", str(tmp_path / "b")])
    a, b = (json.loads((tmp_path / d / "results.json").read_text()) for d in "ab")
    scores = ("aee", "hmc", "hmc_zero", "cosine", "outlier_pct")  # all but the times
    assert {k: a["overall"]["dt1"].get(k) for k in scores} == {k: b["overall"]["dt1"].get(k) for k in scores}
    assert a["method"] == b["method"] and list(a["baselines"]) == list(b["baselines"])
    (tmp_path / "typo.toml").write_text("max_window = 2\n")
    with pytest.raises(ValueError, match=r"\['max_window'\] not options of this command"):
        evaluate_script.main(["--config", str(tmp_path / "typo.toml"), "--out", str(tmp_path / "c")])
    (tmp_path / "bad.toml").write_text("zero = = true\n")
    with pytest.raises(ValueError, match="not valid TOML"):
        evaluate_script.main(["--config", str(tmp_path / "bad.toml"), "--out", str(tmp_path / "d")])
