"""scripts/ship.py: a chunked run that validates after each chunk and ships only improvements,
and continues from the shipped weights when its run folder is gone (a new machine)."""

import json
import subprocess
import sys
from pathlib import Path

import torch

from agents.checkpoint import load_checkpoint

ROOT = Path(__file__).resolve().parents[1]
RECIPE = ["--model", "ev-mgrflownet", "--width", "4", "--data", "synthetic-mini", "--num-envs", "1", "--unroll", "2",
          "--steps", "1000000"]


def _ship(tmp_path, out, *extra):
    cmd = [sys.executable, str(ROOT / "scripts" / "ship.py"), "--name", "tiny", "--out", str(out), "--hours", "0.0005",
           "--chunk-minutes", "0.01", "--val-data", "synthetic-mini", "--val-windows", "1",
           "--weights-dir", str(tmp_path / "weights"), *extra, "--", *RECIPE]
    printed = subprocess.run(cmd, check=True, capture_output=True, text=True).stdout
    return [json.loads(line) for line in (out / "ship.jsonl").read_text().splitlines()], printed


def test_ship_exports_an_improvement_and_a_new_machine_continues_from_it(tmp_path):
    log, printed = _ship(tmp_path, tmp_path / "run")
    assert "--init" not in printed and len(log) == 1 and log[0]["shipped"] and log[0]["best_before"] == float("inf")
    meta = json.loads((tmp_path / "weights" / "tiny.json").read_text())
    assert meta["validation"]["score"] == log[0]["score"] and meta["validation"]["data"] == "synthetic-mini"
    shipped = load_checkpoint(tmp_path / "weights" / "tiny.pt")
    assert all(v.dtype == torch.float16 for v in shipped["model"].values() if v.is_floating_point())
    # a new machine: no run folder, the shipped weights are the start of the next run
    log, printed = _ship(tmp_path, tmp_path / "elsewhere")
    assert f"--init {tmp_path / 'weights' / 'tiny.pt'}" in printed
    config = json.loads((tmp_path / "elsewhere" / "train" / "config.json").read_text())
    started = load_checkpoint(tmp_path / "elsewhere" / "train" / "checkpoint.pt")
    assert config["model"] == "ev-mgrflownet" and started["step"] >= 1
    assert ("shipped" in log[0]) == (log[0]["score"] < log[0]["best_before"])  # ships only an improvement


def test_ship_can_validate_the_network_stepped_through_sub_windows(tmp_path):
    from evflow_cli.commands.ship import validation_score

    log, _ = _ship(tmp_path, tmp_path / "run", "--val-split", "dt")
    meta = json.loads((tmp_path / "weights" / "tiny.json").read_text())
    assert "--split dt" in meta["validation"]["definition"]
    results = meta["evaluation"]
    split, zero = results["baselines"]["model + split dt"], results["baselines"]["zero flow"]
    expected = (split["overall"]["dt1"]["aee"] / zero["overall"]["dt1"]["aee"]
                + split["overall"]["dt4"]["aee"] / zero["overall"]["dt4"]["aee"]) / 2
    assert log[0]["score"] == meta["validation"]["score"] == expected
    plain, _ = validation_score(tmp_path / "run" / "train" / "checkpoint.pt", "synthetic-mini", 1, tmp_path / "v")
    assert plain != expected  # at dt = 4 the split row is another flow
