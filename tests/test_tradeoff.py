"""The proposal-and-finish measurement (evflow_cli/tradeoff.py, scripts/tradeoff.py) and the
still guard (agents/wrappers/still.py)."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from agents.cmax import ContrastMaximisationPolicy
from agents.wrappers import RefinedPolicy, StillGuard, SubWindowPolicy
from envs.windows import Window
from evflow_cli import tradeoff
from evflow_cli.commands.tradeoff import main as tradeoff_main
from losses import window_loss, zero_flow_loss
from tests.recordings import translating_dots, write_translating_recording


class _Constant:
    input_key, voxel_bins, device = "count_image", 5, "cpu"

    def __init__(self, vector):
        self.vector = np.asarray(vector, np.float32)

    def reset(self, mask=None):
        pass

    def act(self, obs, window=None):
        return np.broadcast_to(self.vector[:, None, None], (2, *obs[self.input_key].shape[-2:])).copy()


def _window(rng, velocity):
    events, (t0, t1) = translating_dots(rng, sensor_size=(21, 31), velocity=velocity, duration_us=33_333,
                                        num_dots=60, events_per_s=200_000)
    return Window.of(events, t0, t1)


def test_still_guard_keeps_still_windows_still_and_real_motion_moving(rng):
    obs = {"count_image": np.zeros((2, 21, 31), np.float32)}
    still = _window(rng, (0.0, 0.0))  # dots that do not move: any flow smears them
    invented = StillGuard(_Constant((1.5, -1.0)))
    assert not invented.act(obs, still).any() and (invented.kept, invented.windows) == (0, 1)
    loss = window_loss(torch.full((1, 2, 21, 31), 1.0), still.batch(), flow_scaling=31.0).loss
    assert float(loss) > float(zero_flow_loss(torch.zeros(1, 2, 21, 31), still.batch(),
                                              flow_scaling=31.0).loss)  # why it was refused
    moving = _window(rng, (120.0, -90.0))
    truth = np.array([120.0, -90.0]) * 33_333 / 1e6
    right = StillGuard(_Constant(truth))
    assert np.allclose(right.act(obs, moving), truth[:, None, None]) and right.kept == 1
    empty = Window.of(moving.events[:0], 0, 33_333)
    assert not right.act(obs, empty).any()  # no events: nothing supports motion
    with pytest.raises(ValueError, match="window"):
        right.act(obs)


def test_modes_build_the_policies_they_name():
    assert tradeoff.build_mode("zero", None, 1) is None
    cmax = tradeoff.build_mode("cmax:20", None, 1)
    assert isinstance(cmax, ContrastMaximisationPolicy) and sum(cmax.settings.steps) == 20
    finished = tradeoff.build_mode("split+mid:10@0.5", None, 4)
    assert isinstance(finished, RefinedPolicy) and isinstance(finished.policy, SubWindowPolicy)
    assert finished.settings.grids == (8, 16) and finished.steps == 10 and finished.settings.prior_weight == 0.5
    guarded = tradeoff.build_mode("net+fine:3+still", None, 1)
    assert isinstance(guarded, StillGuard) and isinstance(guarded.policy, RefinedPolicy)
    for bad in ("cmax", "cmax:0", "netto", "net+slow:3", "net+fine:x", "zero+still", "cmax:10+still"):
        with pytest.raises(ValueError, match="mode"):
            tradeoff.build_mode(bad, None, 1)


def test_block_modes_finish_with_the_learned_block_and_need_one():
    from agents.pretrained import default_finish
    from agents.update_block import UpdateBlock
    from agents.wrappers.refine import BLOCK, FinishedPolicy

    block = UpdateBlock(hidden=4)
    with pytest.raises(ValueError, match="--block"):
        tradeoff.build_mode("net+block:4", None, 1)
    one = tradeoff.build_mode("coarse3:2+block:4/8000", None, 4, block=block)
    assert isinstance(one, FinishedPolicy) and one.block is block
    assert [(f.solver, f.steps, f.max_events) for f in one.finishes] == [(BLOCK, 4, 8000)]
    default = tradeoff.build_mode("default+block:3", None, 4, block=block)
    shipped = FinishedPolicy(default.policy, default_finish()).finishes
    # the default's proposals (grids and window lengths) and event bounds, each finished by the block
    assert [(f.solver, f.steps) for f in default.finishes] == [(BLOCK, 3)] * len(shipped)
    assert [(f.coarse, f.splits, f.up_to_frames, f.max_events) for f in default.finishes] == \
        [(f.coarse, f.splits, f.up_to_frames, f.max_events) for f in shipped]
    then = tradeoff.build_mode("default+block:2+solve", None, 4, block=block)
    assert [(f.solver, f.steps, f.block_steps) for f in then.finishes] == \
        [(f.solver, f.steps, 2) for f in shipped]
    for bad in ("default+block:x", "net+block:4x2", "default+block:2+cmax"):
        with pytest.raises(ValueError, match="mode"):
            tradeoff.build_mode(bad, None, 1, block=block)


def test_measure_scores_every_mode_on_the_same_windows(tmp_path, rng):
    paths = [write_translating_recording(tmp_path / f"dots{i}.h5", rng, duration_us=200_000) for i in range(2)]
    points = tradeoff.measure([str(p) for p in paths], "dots", ["zero", "split", "cmax:6"], [1, 2], max_windows=3,
                              progress=False, echo=lambda line: None)
    assert [(p.dt, p.mode) for p in points] == [(1, "zero"), (1, "split"), (1, "cmax:6"),
                                                (2, "zero"), (2, "split"), (2, "cmax:6")]
    frame = np.hypot(200.0, -100.0) * 0.030  # the dots' displacement over one 30 ms frame
    for p in points:
        assert len(p.aee) == 2 and p.windows == 6  # both sequences, 3 windows each, every mode alike
        if p.mode == "zero":
            assert p.mean_aee == pytest.approx(frame * p.dt, rel=1e-4)  # zero flow's error is the motion itself
        else:
            assert np.isfinite(p.mean_aee) and p.ms > 0
    md = tradeoff.table(points, reference="cmax:6")
    assert md.count("| cmax:6 |") == 2 and "| 1.00x |" in md and "(2 sequences, 6 windows)" in md
    tradeoff.write_json(points, tmp_path / "out" / "points.json")
    again = json.loads((tmp_path / "out" / "points.json").read_text())
    assert [(r["dt"], r["mode"], r["aee"]) for r in again] == [(p.dt, p.mode, p.mean_aee) for p in points]


def test_command_writes_its_table_and_refuses_a_typo_before_measuring(tmp_path, rng, capsys):
    path = write_translating_recording(tmp_path / "dots.h5", rng, duration_us=150_000)
    with pytest.raises(ValueError, match="cmax:N|steps"):
        tradeoff_main(["--data", str(path), "--modes", "zero", "cmax:x", "--out", str(tmp_path / "bad")])
    assert not (tmp_path / "bad").exists()
    out = tmp_path / "run"
    assert tradeoff_main(["--data", str(path), "--modes", "zero", "net", "cmax:4", "--dt", "1", "--max-windows", "2",
                          "--reference", "cmax:4", "--out", str(out), "--no-progress"]) == 0
    assert "| net |" in (out / "tradeoff.md").read_text() and not (out / "tradeoff.partial.json").exists()
    rows = json.loads((out / "tradeoff.json").read_text())
    assert [r["mode"] for r in rows] == ["zero", "net", "cmax:4"]


def test_replot_reads_the_points_a_run_wrote(tmp_path, rng):
    path = write_translating_recording(tmp_path / "dots.h5", rng, duration_us=150_000)
    out = tmp_path / "run"
    assert tradeoff_main(["--data", str(path), "--modes", "zero", "net", "cmax:4", "--dt", "1", "--max-windows", "2",
                          "--reference", "cmax:4", "--out", str(out), "--no-progress"]) == 0
    again = tradeoff.load_points(out / "tradeoff.json")
    assert tradeoff.table(again, reference="cmax:4") == (out / "tradeoff.md").read_text().rstrip("\n")
    assert tradeoff_main(["--replot", str(out / "tradeoff.json"), "--reference", "cmax:4", "--out", str(tmp_path / "re")]) == 0
    assert (tmp_path / "re" / "tradeoff.md").read_text() == (out / "tradeoff.md").read_text()
    families = {m: tradeoff.family(m) for m in ("zero", "net", "split+fine:3", "net+mid:10/800", "split+cmax:3",
                                                "cmax:30", "default", "net+fine:3+still")}
    assert families == {"zero": None, "net": "network alone", "split+fine:3": "+ fine", "net+mid:10/800": "+ mid",
                        "split+cmax:3": "+ cmax", "cmax:30": "cmax alone", "default": "the default's mode",
                        "net+fine:3+still": "other"}
