"""train.py --logger tensorboard (evflow_cli/tensorboard_log.py): the event files hold the step and
validation scalars of metrics.jsonl and a flow panel per validation; without the optional
'tensorboard' extra the option is refused before any work, saying how to install it."""

from __future__ import annotations

import json
import sys

import numpy as np
import pytest

from evflow_cli.commands import train as train_command
from tests.recordings import write_translating_recording


def run_options(recording, out) -> list[str]:
    return ["--data", str(recording), "--width", "4", "--num-envs", "1", "--unroll", "2", "--steps", "2",
            "--device", "cpu", "--out", str(out), "--val-data", str(recording), "--val-every", "1",
            "--val-windows", "2", "--no-progress", "--logger", "tensorboard"]


def test_tensorboard_event_files_hold_the_scalars_and_a_flow_panel(tmp_path):
    pytest.importorskip("tensorboard", reason="the optional 'tensorboard' extra is not installed")
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    recording = write_translating_recording(tmp_path / "dots.h5", np.random.default_rng(3), sensor_size=(32, 32))
    assert train_command.main(run_options(recording, tmp_path / "run")) == 0
    board = EventAccumulator(str(tmp_path / "run" / "tensorboard"), size_guidance={"images": 0, "scalars": 0})
    board.Reload()
    tags = board.Tags()
    assert {"train/loss", "train/lr", "train/zero_flow_loss", "train/grad_norm", "val/aee_model", "val/aee_zero",
            "val/hmc_model", "val/hmc_zero"} <= set(tags["scalars"])
    rows = [json.loads(line) for line in (tmp_path / "run" / "metrics.jsonl").read_text().splitlines()]
    steps = [row for row in rows if "loss" in row]
    validations = [row for row in rows if "val_aee_model" in row]
    assert [e.step for e in board.Scalars("train/loss")] == [1, 2] and len(validations) == 2
    assert [e.value for e in board.Scalars("train/loss")] == pytest.approx([row["loss"] for row in steps], rel=1e-6)
    assert [e.value for e in board.Scalars("val/aee_model")] == pytest.approx(
        [row["val_aee_model"] for row in validations], rel=1e-6)
    images = board.Images("val/flow")
    assert [image.step for image in images] == [1, 2] and images[0].width > 2 * 32  # events, flows, legend side by side


def test_tensorboard_missing_is_refused_before_any_work(tmp_path, monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "tensorboard", None)  # as if not installed: its import fails
    assert train_command.main(run_options(tmp_path / "absent.h5", tmp_path / "run")) == 2
    err = capsys.readouterr().err
    assert "--logger tensorboard needs the 'tensorboard' package" in err
    assert "pip install evflow-gym[tensorboard]" in err
    assert not (tmp_path / "run").exists()
