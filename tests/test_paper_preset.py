"""The paper's training recipe as a named preset (scripts/train.py --preset paper)."""

import json
import math
from pathlib import Path

import pytest

import losses.window as window_module
from agents.learner import PRESETS, Learner, TrainConfig, preset_config

ROOT = Path(__file__).resolve().parents[1]
from evflow_cli.commands import train as train_script  # noqa: E402


def test_preset_sets_the_paper_recipe_and_options_beside_it_win():
    cfg = train_script.config_from_args(train_script.parse_args(["--preset", "paper"]))
    assert (cfg.model, cfg.width, cfg.input, cfg.lr, cfg.unroll) == ("ev-mgrflownet", "paper", "count_image", 1e-4, 10)
    assert (cfg.loss, cfg.loss_mode, cfg.loss_scales) == ("hmc", "accumulated", "all")
    assert cfg.border_penalty == TrainConfig().border_penalty > 0  # the border rule stays on
    assert cfg == preset_config("paper")
    cfg = train_script.config_from_args(train_script.parse_args(
        ["--preset", "paper", "--border-penalty", "0", "--width", "4", "--upsampling", "nearest"]))
    assert (cfg.border_penalty, cfg.width, cfg.upsampling, cfg.loss_mode) == (0.0, 4, "nearest", "accumulated")
    assert cfg == preset_config("paper", border_penalty=0.0, width=4, upsampling="nearest")
    with pytest.raises(SystemExit):
        train_script.parse_args(["--preset", "nonsense"])
    with pytest.raises(ValueError, match="unknown preset"):
        preset_config("nonsense")


def test_bad_choices_are_refused_naming_the_field():
    with pytest.raises(ValueError, match="loss_scales.*'all', 'finest'"):
        Learner(preset_config("paper", loss_scales="coarsest", data="synthetic-mini"))
    with pytest.raises(ValueError, match="reference_times"):
        Learner(preset_config("paper", reference_times="middle", data="synthetic-mini"))


def test_paper_preset_update_is_one_loss_over_the_windows_of_all_scales(monkeypatch):
    """Sequential learning: one accumulated L_HMC per update over the L = 10 windows, each
    window contributing its four scales' flows, the border rule weighted by the zero-flow loss."""
    calls = []
    original = window_module._accumulated  # what losses.accumulated_window_loss evaluates

    def spy(flows, batches, **kwargs):
        calls.append(([len(f) if isinstance(f, list) else 1 for f in flows], len(batches), kwargs))
        return original(flows, batches, **kwargs)

    monkeypatch.setattr(window_module, "_accumulated", spy)
    learner = Learner(preset_config("paper", width=2, data="synthetic-mini", num_envs=1))
    try:
        stats = learner.update()
    finally:
        learner.close()
    assert math.isfinite(stats["loss"]) and stats["windows"] == 10
    (zero_scales, zero_k, zero_kwargs), (scales, k, kwargs) = calls  # zero-flow reference, then the loss
    assert zero_k == k == 10 and scales == [4] * 10 and zero_scales == [1] * 10
    assert kwargs["reference_times"] == "window" and kwargs["upsampling"] == "bilinear"
    assert float(kwargs["weights"]["border_penalty"].sum()) > 0 and zero_kwargs["weights"]["border_penalty"] == 0.0
    assert kwargs["outside_weight"] is kwargs["weights"]["border_penalty"] and zero_kwargs["outside_weight"] == 0.0


@pytest.mark.parametrize("extra", [[], ["--border-penalty", "0", "--loss-scales", "finest", "--reference-times", "events",
                                        "--at-normalisation", "sum", "--upsampling", "nearest"]])
def test_paper_preset_trains_end_to_end_on_synthetic_mini(tmp_path, extra):
    out = tmp_path / "paper"
    train_script.main(["--preset", "paper", "--data", "synthetic-mini", "--width", "2", "--num-envs", "1",
                       "--steps", "2", "--out", str(out), "--val-data", "", "--no-progress", "--device", "cpu", *extra])
    config = json.loads((out / "config.json").read_text())
    for name, value in PRESETS["paper"].items():
        if name != "width" and f"--{name.replace('_', '-')}" not in extra:
            assert config[name] == value, name
    assert config["border_penalty"] == (0.0 if extra else TrainConfig().border_penalty)
    rows = [json.loads(line) for line in (out / "metrics.jsonl").read_text().splitlines()]
    assert [r["step"] for r in rows] == [1, 2]
    assert all(math.isfinite(r["loss"]) and r["windows"] == 10 for r in rows)
    assert (out / "checkpoint.pt").exists()
