"""Precomputed teacher targets (agents/teacher.py): they land in the env's frame exactly as the
env's own ground truth does (crop, flips), they are the solver's output, an interrupted run
resumes, bad files are named, and a teacher run trains on them."""

import dataclasses
import json
from pathlib import Path

import h5py
import numpy as np
import pytest
import torch
import torch.nn.functional as F

from agents.cmax import CMaxSettings
from agents.policy import ZeroFlowPolicy
from agents.rollout import rollout
from agents.teacher import (
    FORMAT,
    TeacherCacheError,
    TeacherSettings,
    TeacherTargets,
    compute_teacher_targets,
    count_windows,
    derive_targets,
    merge_targets,
    score_targets,
)
from envs.env import EventFlowEnv
from envs.events import Events
from envs.readers.h5 import write_h5
from losses import EventBatch, contrast_maximisation_flow
from tests.recordings import translating_dots, write_translating_recording

ROOT = Path(__file__).resolve().parents[1]
from evflow_cli.commands import teacher_targets as teacher_targets_command  # noqa: E402
from evflow_cli.commands import train as train_script  # noqa: E402

TINY = TeacherSettings(grids=(2, 4), steps=3)


def _write_ground_truth_targets(path: Path, data, sizes=(1, 2)) -> Path:
    """A target file in the documented layout whose "grid" is each window's full-resolution
    ground truth (upsampling to the same size is the identity): its targets must equal the
    env's flow_gt whatever the crop and flips."""
    env = EventFlowEnv(data, compute_reward=False)
    with h5py.File(path, "w") as f:
        f.attrs["config"] = json.dumps({"format": FORMAT, "data": data, "window_sizes": list(sizes),
                                        "sensor_size": list(env.sensor_size)})
        f.attrs["complete"] = True
        for index, name in enumerate(env.sequence_names):
            reader = env.sources[index].reader()
            bounds, grids = [], []
            for k in sizes:
                grid = np.asarray(reader.flow_timestamps(), np.int64)[::k]
                for t0, t1 in zip(grid[:-1], grid[1:]):
                    bounds.append((t0, t1))
                    grids.append(reader.flow_between(int(t0), int(t1))[0])
            f[f"{name}/bounds"] = np.array(bounds, np.int64)
            f[f"{name}/grid"] = np.stack(grids).astype(np.float32)
    env.close()
    return path


def test_targets_land_in_the_env_frame_like_its_ground_truth(tmp_path):
    path = _write_ground_truth_targets(tmp_path / "gt.h5", "synthetic-mini")
    targets = TeacherTargets(path)
    env = EventFlowEnv("synthetic-mini", window_size=[1, 2], crop=(40, 48), random_crop=True, flips=True,
                       compute_reward=False)
    seen_flips, seen_crops = set(), set()
    for seed in range(8):
        _, info = env.reset(seed=seed)
        for _ in range(2):
            window = info["window"]
            target = targets.target(info["sequence"], window.t_start, window.t_end, info["crop"], info["flips"])
            assert target.shape == (2, 40, 48)
            np.testing.assert_allclose(target.numpy(), info["flow_gt"], rtol=0, atol=1e-5)
            seen_flips.add(tuple(bool(v) for v in info["flips"][:2]))
            seen_crops.add(tuple(int(v) for v in info["crop"][:2]))
            _, _, _, _, info = env.step(np.zeros((2, 40, 48), np.float32))
    assert len(seen_flips) >= 3 and len(seen_crops) >= 3  # the mapping was exercised, not just the identity


def test_computed_targets_are_the_solvers_flow_and_an_interrupted_run_resumes(tmp_path):
    recs = [write_translating_recording(tmp_path / f"dots{i}.h5", np.random.default_rng(i), sensor_size=(24, 32))
            for i in range(2)]
    out = tmp_path / "targets.h5"
    parts = out.with_name(out.name + ".parts")

    def interrupt(n, name):  # stop inside the second recording: the first is on disk
        if name == "dots1":
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        compute_teacher_targets(recs, out, window_sizes=(1, 2), settings=TINY, batch_size=4, progress=interrupt)
    assert not out.exists()
    assert sorted(f.name for f in parts.iterdir()) == ["00000.npz", "config.json"]  # no temporary left
    with np.load(parts / "00000.npz") as part:
        assert str(part["name"]) == "dots0"
        first = part["grid"]
    (parts / "00001.npz.tmp-999999999").write_bytes(b"cut by a kill")  # a killed write: ignored, not read
    with pytest.raises(TeacherCacheError, match="unfinished run with other settings"):
        compute_teacher_targets(recs, out, window_sizes=(1,), settings=TINY)
    done = []
    compute_teacher_targets(recs, out, window_sizes=(1, 2), settings=TINY, batch_size=4,
                            progress=lambda n, name: done.append((name, n)))
    assert out.exists() and not parts.exists()
    assert done[0] == ("dots0", 15)  # skipped, counted once
    targets = TeacherTargets(out)
    assert len(targets) == count_windows(recs, (1, 2)) == sum(n for _, n in done) == 2 * (10 + 5)
    with h5py.File(out, "r") as f:
        np.testing.assert_array_equal(f["dots0/grid"][()], first)
    rec = recs[1]
    # one window, solved alone here: the stored grid upsampled is the solver's flow
    env = EventFlowEnv(rec, window_size=2, compute_reward=False)
    _, info = env.reset(options={"sequence": 0})
    _, _, _, _, info = env.step(np.zeros((2, 24, 32), np.float32))
    batch = EventBatch.from_windows([info["window"]])
    direct = contrast_maximisation_flow(batch, 24, 32, grids=TINY.grids, steps=TINY.steps, lr=2 * TINY.lr_per_frame,
                                        flow_scaling=TINY.flow_scaling, weights=TINY.weights)[0]
    stored = targets.target(info["sequence"], info["window"].t_start, info["window"].t_end)
    assert direct.abs().max() > 0.01  # the solver moved: the comparison is not zero against zero
    torch.testing.assert_close(stored, direct, rtol=1e-4, atol=1e-4)


def test_bad_target_files_are_named(tmp_path):
    with pytest.raises(TeacherCacheError, match="no such file"):
        TeacherTargets(tmp_path / "missing.h5")
    (tmp_path / "text.h5").write_text("not h5")
    with pytest.raises(TeacherCacheError, match="text.h5: not an h5 file"):
        TeacherTargets(tmp_path / "text.h5")
    path = _write_ground_truth_targets(tmp_path / "gt.h5", "synthetic-mini", sizes=(1,))
    targets = TeacherTargets(path)
    with pytest.raises(TeacherCacheError, match=r"gt.h5: no window \[0, 5\) of recording 'synthetic-mini-0'.*sizes \[1\]"):
        targets.target("synthetic-mini-0", 0, 5)
    with h5py.File(path, "a") as f:
        f.attrs["complete"] = False
    with pytest.raises(TeacherCacheError, match="incomplete"):
        TeacherTargets(path)
    with pytest.raises(ValueError, match="teacher_cache is for loss 'teacher'"):
        train_script.main(["--data", "synthetic-mini", "--loss", "hmc", "--teacher-cache", str(path), "--steps", "0",
                           "--out", str(tmp_path / "run"), "--no-progress"])


def test_a_teacher_run_regresses_onto_the_cached_targets(tmp_path):
    """With ground-truth grids as the 'teacher' and a network held at zero flow, the logged
    loss is the mean ground-truth magnitude over the unroll's windows (all pixels)."""
    path = _write_ground_truth_targets(tmp_path / "gt.h5", "synthetic-mini")
    out = tmp_path / "run"
    train_script.main(["--data", "synthetic-mini", "--model", "ev-flownet", "--width", "4", "--num-envs", "2",
                       "--unroll", "2", "--steps", "2", "--lr", "0", "--head-init", "0", "--loss", "teacher",
                       "--teacher-pixels", "all", "--teacher-cache", str(path), "--crop", "32", "32", "--random-crop",
                       "--val-data", "", "--out", str(out), "--no-progress"])
    rows = [json.loads(line) for line in (out / "metrics.jsonl").read_text().splitlines() if "loss" in json.loads(line)]
    assert len(rows) == 2
    for row in rows:
        assert row["zero_flow_teacher"] > 0.1  # synthetic-mini moves 1-8 px per frame
        assert row["loss"] == pytest.approx(row["zero_flow_teacher"], rel=1e-6)
    assert json.loads((out / "config.json").read_text())["teacher_cache"] == str(path)
    # the shipped model's provenance says how its targets were made
    from agents.pretrained import export_pretrained, pretrained_info

    export_pretrained(out / "checkpoint.pt", "tiny", {"command": "train.py ..."}, directory=tmp_path / "weights")
    with h5py.File(path, "r") as f:
        made = json.loads(f.attrs["config"])
    assert pretrained_info("tiny", tmp_path / "weights")["teacher_targets"] == {"file": "gt.h5", "config": made}


def test_upsampling_a_same_size_grid_is_the_identity():
    """The ground-truth files above rely on it."""
    grid = torch.randn(1, 2, 7, 9)
    torch.testing.assert_close(F.interpolate(grid, size=(7, 9), mode="bilinear", align_corners=False), grid)


def _windows(path, name):
    """{(t_start, t_end): grid} of one recording in a target file, in time order."""
    with h5py.File(path, "r") as f:
        return {tuple(b): g for b, g in zip(f[name]["bounds"][()].tolist(), f[name]["grid"][()])}


def test_derived_targets_are_the_long_windows_velocity_times_each_windows_duration(tmp_path):
    rec = write_translating_recording(tmp_path / "dots.h5", np.random.default_rng(3), sensor_size=(24, 32))
    solved = compute_teacher_targets([rec], tmp_path / "solved.h5", window_sizes=(1, 2), settings=TINY)
    long = _windows(solved, "dots")
    two = sorted(b for b in long if any(b[0] < c[0] < b[1] for c in long))  # the 2-frame windows contain a start
    assert len(two) >= 4 and min(np.abs(long[w]).max() for w in two) > 0.01  # moving: not zero against zero

    derived = _windows(derive_targets(solved, tmp_path / "d.h5", from_size=2, window_sizes=(1, 2)), "dots")
    assert set(derived) == set(long)
    for a, b in two:  # the long windows themselves: unchanged
        np.testing.assert_allclose(derived[(a, b)], long[(a, b)], rtol=1e-5, atol=1e-6)
        for (c, d) in derived:  # a 1-frame window inside: the same velocity, its own duration
            if a <= c and d <= b and (c, d) != (a, b):
                np.testing.assert_allclose(derived[(c, d)], long[(a, b)] * (d - c) / (b - a), rtol=1e-5, atol=1e-6)

    smoothed = _windows(derive_targets(solved, tmp_path / "s.h5", from_size=2, smooth=1, window_sizes=(2,)), "dots")
    velocity = [long[w] / (w[1] - w[0]) for w in two]
    for i in range(1, len(two) - 1):  # weights 1, 2, 1 over the neighbours
        expected = (velocity[i - 1] + 2 * velocity[i] + velocity[i + 1]) / 4 * (two[i][1] - two[i][0])
        np.testing.assert_allclose(smoothed[two[i]], expected, rtol=1e-5, atol=1e-6)
    assert TeacherTargets(tmp_path / "s.h5").config["derived"]["smooth"] == 1

    with pytest.raises(TeacherCacheError, match="no 4-frame windows"):
        derive_targets(solved, tmp_path / "x.h5", from_size=4)
    assert not (tmp_path / "x.h5").exists()


def test_targets_of_the_first_windows_only_derive_and_score_on_their_span(tmp_path):
    rec = write_translating_recording(tmp_path / "dots.h5", np.random.default_rng(4), sensor_size=(24, 32))
    solved = compute_teacher_targets([rec], tmp_path / "first.h5", window_sizes=(1, 2), settings=TINY, max_windows=3)
    assert len(TeacherTargets(solved)) == 6 == count_windows([rec], (1, 2), 3)
    derived = _windows(derive_targets(solved, tmp_path / "d.h5", from_size=2, window_sizes=(1, 2)), "dots")
    assert len(derived) == 3 + 6  # the 3 solved 2-frame windows and the 6 1-frame windows inside them
    scores = score_targets(tmp_path / "d.h5", max_windows=3, window_sizes=(1,))
    assert list(scores) == ["1"] and scores["1"]["windows"] == 3 and scores["1"]["aee"] < scores["1"]["aee_zero"]


def test_merged_targets_take_each_window_length_from_its_part(tmp_path):
    rec = write_translating_recording(tmp_path / "dots.h5", np.random.default_rng(5), sensor_size=(24, 32))
    a = compute_teacher_targets([rec], tmp_path / "a.h5", window_sizes=(1, 2), settings=TINY, max_windows=3)
    strong = dataclasses.replace(TINY, steps=TINY.steps + 5 if isinstance(TINY.steps, int) else TINY.steps)
    b = compute_teacher_targets([rec], tmp_path / "b.h5", window_sizes=(2, 4), settings=strong, max_windows=3)
    one, two = _windows(a, "dots"), _windows(b, "dots")
    merged = _windows(merge_targets([(a, [1]), (b, [2, 4])], tmp_path / "m.h5", dtype=np.float16), "dots")
    frame = min(t1 - t0 for t0, t1 in one)
    expected = {w: g for w, g in one.items() if w[1] - w[0] == frame}
    expected.update(two)
    assert set(merged) == set(expected) and len(merged) == 3 + len(two)
    for w, g in expected.items():  # float16: within its rounding
        np.testing.assert_allclose(merged[w], g, rtol=1e-3, atol=1e-3)
    assert TeacherTargets(tmp_path / "m.h5").config["window_sizes"] == [1, 2, 4]
    with pytest.raises(ValueError, match="more than one part"):
        merge_targets([(a, [2]), (b, [2])], tmp_path / "x.h5")
    assert not (tmp_path / "x.h5").exists()


def test_the_evidence_prior_weighs_each_window_by_its_events_and_is_recorded(tmp_path):
    """TeacherSettings.evidence_prior: each stored window is the solver's flow with prior weight
    C / that window's events (checked against a direct solve of one window), the file's config
    names C, and a file without it names none (as the files made before it)."""
    rec = write_translating_recording(tmp_path / "dots.h5", np.random.default_rng(3), sensor_size=(24, 32))
    free = dataclasses.replace(TINY, steps=20, lr_per_frame=0.3)
    held = dataclasses.replace(free, evidence_prior=1e7)
    out = compute_teacher_targets([rec], tmp_path / "held.h5", window_sizes=(2,), settings=held, batch_size=4)
    plain = compute_teacher_targets([rec], tmp_path / "plain.h5", window_sizes=(2,), settings=free, batch_size=4)
    assert TeacherTargets(out).config["evidence_prior"] == 1e7 and "evidence_prior" not in TeacherTargets(plain).config
    env = EventFlowEnv(rec, window_size=2, compute_reward=False)
    _, info = env.reset(options={"sequence": 0})
    _, _, _, _, info = env.step(np.zeros((2, 24, 32), np.float32))
    window = info["window"]
    solve = dict(grids=free.grids, steps=free.steps, lr=2 * free.lr_per_frame, flow_scaling=free.flow_scaling,
                 weights=free.weights)
    direct = contrast_maximisation_flow(EventBatch.from_windows([window]), 24, 32,
                                        prior_weight=1e7 / len(window.events), **solve)[0]
    stored = TeacherTargets(out).target(info["sequence"], window.t_start, window.t_end)
    unheld = TeacherTargets(plain).target(info["sequence"], window.t_start, window.t_end)
    torch.testing.assert_close(stored, direct, rtol=1e-4, atol=1e-4)
    assert unheld.abs().max() > 0.5 and stored.abs().max() < 0.3 * unheld.abs().max()  # the prior holds it


def _dense_then_sparse_recording(path: Path, keep_every: int = 8) -> Path:
    """Translating dots whose second half keeps one event in ``keep_every``: windows of the same
    motion with about ``keep_every`` times fewer events."""
    events, (t0, t1) = translating_dots(np.random.default_rng(7), sensor_size=(24, 32))
    index = np.arange(len(events.t))
    keep = (events.t < (t0 + t1) // 2) | (index % keep_every == 0)
    events = Events.create(events.x[keep], events.y[keep], events.t[keep], events.p[keep], events.sensor_size)
    grid = np.arange(t0, t1 + 1, 30_000)
    flows = [(int(a), int(b), np.stack([np.full((24, 32), 200.0 * (b - a) / 1e6, np.float32),
                                        np.full((24, 32), -100.0 * (b - a) / 1e6, np.float32)]), np.ones((24, 32), bool))
             for a, b in zip(grid[:-1], grid[1:])]
    return write_h5(path, events, flows=flows, t_start_us=t0, t_end_us=t1, name=path.stem)


def test_each_window_of_a_batch_has_its_own_evidence_prior_weight(tmp_path):
    """Dense and sparse windows solved in one batch: each stored target is the direct solve of
    that window alone with weight C / its own events, not one weight shared by the batch."""
    rec = _dense_then_sparse_recording(tmp_path / "dots.h5")
    settings = dataclasses.replace(TINY, steps=20, lr_per_frame=0.3, evidence_prior=3000.0)
    out = compute_teacher_targets([rec], tmp_path / "held.h5", window_sizes=(2,), settings=settings, batch_size=16)
    targets = TeacherTargets(out)
    env = EventFlowEnv(rec, window_size=2, compute_reward=False)
    windows = [step.window for step in rollout(ZeroFlowPolicy(), env, options={"sequence": 0})]
    counts = [len(w.events) for w in windows]
    assert len(windows) >= 4 and max(counts) > 5 * min(counts)  # dense and sparse in the one batch
    solve = dict(grids=settings.grids, steps=settings.steps, lr=2 * settings.lr_per_frame,
                 flow_scaling=settings.flow_scaling, weights=settings.weights)
    shared = settings.evidence_prior / np.mean(counts)
    for window, n in zip(windows, counts):
        direct = contrast_maximisation_flow(EventBatch.from_windows([window]), 24, 32,
                                            prior_weight=settings.evidence_prior / n, **solve)[0]
        stored = targets.target("dots", window.t_start, window.t_end)
        torch.testing.assert_close(stored, direct, rtol=1e-4, atol=1e-4)
        if n == min(counts):  # the sparse window: the batch's mean weight would give another flow
            other = contrast_maximisation_flow(EventBatch.from_windows([window]), 24, 32, prior_weight=shared,
                                               **solve)[0]
            assert (other - direct).abs().max() > 1e-2


def test_merged_targets_keep_each_parts_settings_and_join_other_data_only_on_other_recordings(tmp_path):
    rec = write_translating_recording(tmp_path / "dots.h5", np.random.default_rng(5), sensor_size=(24, 32))
    other = write_translating_recording(tmp_path / "other.h5", np.random.default_rng(6), sensor_size=(24, 32))
    a = compute_teacher_targets([rec], tmp_path / "a.h5", window_sizes=(1,), settings=TINY, max_windows=2)
    held = dataclasses.replace(TINY, evidence_prior=10.0)
    b = compute_teacher_targets([rec], tmp_path / "b.h5", window_sizes=(2,), settings=held, max_windows=2)
    config = TeacherTargets(merge_targets([(a, [1]), (b, [2])], tmp_path / "m.h5")).config
    assert [part["config"].get("evidence_prior") for part in config["merged_from"]] == [None, 10.0]
    assert [part["config"]["window_sizes"] for part in config["merged_from"]] == [[1], [2]]
    assert "evidence_prior" not in config and "grids" not in config  # no one solver's settings claimed for all
    # other data, other recordings: one file over both (two training splits), each window its part's
    c = compute_teacher_targets([other], tmp_path / "c.h5", window_sizes=(2,), settings=TINY, max_windows=2)
    joined = TeacherTargets(merge_targets([(a, [1]), (c, [2])], tmp_path / "j.h5"))
    assert joined.config["data"] == [str(rec), str(other)]
    for part, name in ((a, "dots"), (c, "other")):
        with h5py.File(part) as f:
            for (t0, t1), grid in zip(f[f"{name}/bounds"][()], f[f"{name}/grid"][()]):
                np.testing.assert_array_equal(joined.grid(name, t0, t1).numpy(), grid)
    # other data holding a recording of the same name: refused, nothing written
    twin = write_translating_recording(tmp_path / "twin" / "dots.h5", np.random.default_rng(7), sensor_size=(24, 32))
    d = compute_teacher_targets([twin], tmp_path / "d.h5", window_sizes=(2,), settings=TINY, max_windows=2)
    with pytest.raises(ValueError, match="for recording dots that a part of other data"):
        merge_targets([(a, [1]), (d, [2])], tmp_path / "x.h5")
    assert not (tmp_path / "x.h5").exists()


def test_deriving_from_a_file_that_lacks_long_windows_names_it(tmp_path):
    rec = write_translating_recording(tmp_path / "dots.h5", np.random.default_rng(8), sensor_size=(24, 32))
    solved = compute_teacher_targets([rec], tmp_path / "solved.h5", window_sizes=(1, 2), settings=TINY)
    with h5py.File(solved, "r+") as f:  # the 2-frame windows of the recording lost
        bounds, grid = f["dots/bounds"][()], f["dots/grid"][()]
        short = bounds[:, 1] - bounds[:, 0] == (bounds[:, 1] - bounds[:, 0]).min()
        del f["dots/bounds"], f["dots/grid"]
        f["dots/bounds"], f["dots/grid"] = bounds[short], grid[short]
    with pytest.raises(TeacherCacheError, match=r"solved.h5: no window \[.*of recording 'dots'"):
        derive_targets(solved, tmp_path / "d.h5", from_size=2, window_sizes=(1,))
    assert not (tmp_path / "d.h5").exists()


@pytest.mark.parametrize("field, value", [("evidence_prior", -1.0), ("steps", (3,)), ("steps", -1), ("grids", ()),
                                          ("lr_per_frame", 0.0), ("sensor_scales", (2, 1, 1, 1))])
def test_solver_settings_that_cannot_run_are_refused_where_they_are_made(field, value):
    with pytest.raises(ValueError, match=field):
        dataclasses.replace(TINY, **{field: value})
    with pytest.raises(ValueError, match=field):
        dataclasses.replace(CMaxSettings(), **{field: value})


def test_solver_options_without_a_solve_are_an_error(tmp_path, capsys):
    with pytest.raises(SystemExit):
        teacher_targets_command.main(["--derive-from", str(tmp_path / "a.h5"), "--evidence-prior", "3",
                                      "--out", str(tmp_path / "d.h5")])
    assert "--evidence-prior set the solve, which --derive-from does not run" in capsys.readouterr().err
    assert not (tmp_path / "d.h5").exists()
