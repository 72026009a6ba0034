"""Hostile input: files that are corrupt, contradictory or aimed at the user's data, and commands
that would lose work. Each row of ``HOSTILE`` builds one such case and names the error it must
raise (a clear message naming the file or option, the bad value and what was expected); the
tests after the table check what must survive (the user's files, no temporaries)."""

from __future__ import annotations

import hashlib
import os
import pickle
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest
import torch

from agents.checkpoint import CheckpointError, load_checkpoint, rng_state, save_checkpoint, upgrade_checkpoint
from envs.env import EventFlowEnv
from envs.h5format import FormatError, H5Reader, write_h5
from envs.readers import open_recording
from envs.readers.convert import convert_recording
from envs.readers.dsec import DSECReader
from envs.readers.hagenaars import HagenaarsReader
from envs.readers.mvsec import MVSECReader
from envs.readers.text import TextReader
from tests.conftest import random_events
from tests.recordings import write_translating_recording
from tests.test_readers import write_dsec, write_hagenaars, write_mvsec

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "scripts"))  # export_model is tested as a script
from agents.commands import convert as convert_script  # noqa: E402
from agents.commands import train as train_script  # noqa: E402


def _stream(n=2_000, sensor_size=(20, 30), span_us=200_000, seed=0):
    rng = np.random.default_rng(seed)
    h, w = sensor_size
    t = np.sort(rng.integers(0, span_us, n)).astype(np.int64)
    return rng.integers(0, w, n), rng.integers(0, h, n), t, rng.integers(0, 2, n)


def _mvsec(tmp: Path, *, x_value=None, nan_at=None) -> Path:
    x, y, t, p = _stream(sensor_size=(260, 346))
    path = write_mvsec(tmp, "indoor_flying1", x, y, t, p)
    with h5py.File(path, "a") as f:
        ev = f["davis/left/events"]
        if x_value is not None:
            ev[700, 0] = x_value
        if nan_at is not None:
            ev[nan_at, 2] = np.nan
    return path


def _hagenaars(tmp: Path, nan_at: int) -> Path:
    x, y, t, p = _stream()
    path = write_hagenaars(tmp / "seq.h5", x, y, t, p)
    with h5py.File(path, "a") as f:
        f["events/ts"][nan_at] = np.nan
    return path


def _text(tmp: Path, line: str) -> Path:
    path = tmp / "events.txt"
    path.write_text("0.000100 3 4 1\n0.000200 5 6 0\n" + line + "\n0.000400 7 8 1\n")
    return path


def _project(tmp: Path, edit) -> Path:
    events = random_events(np.random.default_rng(0), 3_000, t_span=(0, 50_000))
    path = write_h5(tmp / "rec.h5", events)
    with h5py.File(path, "a") as f:
        edit(f)
    return path


def _set_ms_to_idx(values):
    def edit(f):
        del f["ms_to_idx"]
        f["ms_to_idx"] = values(len(f["events/t"]))
    return edit


def _dsec(tmp: Path, edit) -> Path:
    x, y, t, p = _stream(20_000, (480, 640), 100_000)
    path = write_dsec(tmp / "seq" / "events" / "left", x, y, t, p, compression=False)
    with h5py.File(path, "a") as f:
        edit(f)
    return path


def _cut(f, key, length):
    values = f[key][:length]
    del f[key]
    f[key] = values


def _training_run(tmp: Path, name="run", extra=()) -> Path:
    data = write_translating_recording(tmp / "dots.h5", np.random.default_rng(3), sensor_size=(32, 32))
    out = tmp / name
    train_script.main(["--data", str(data), "--width", "4", "--num-envs", "1", "--unroll", "1", "--steps", "1",
                       "--out", str(out), "--val-data", "", "--no-progress", *extra])
    return out


def _exported(tmp: Path) -> Path:
    import export_model

    run = _training_run(tmp)
    export_model.main([str(run / "checkpoint.pt"), "--name", "tiny", "--dir", str(tmp / "weights")])
    return tmp / "weights" / "tiny.pt"


class _RunsCode:
    """Unpickling this creates a marker file: what a hostile .pt could do instead."""

    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self):
        return (Path.touch, (self.marker,))


def _pickled_code(tmp: Path) -> Path:
    path = tmp / "evil.pt"
    with open(path, "wb") as f:
        pickle.dump({"format": "evflow-checkpoint", "model_name": "ev-flownet", "model_config": {}, "model": {},
                     "payload": _RunsCode(tmp / "code-ran")}, f, protocol=2)
    return path


def _old_format(tmp: Path) -> Path:
    """A checkpoint as written before the safe format: numpy arrays pickled as objects."""
    path = tmp / "old.pt"
    torch.save({"format": "evflow-checkpoint", "version": 1, "model_name": "ev-flownet", "model_config": {},
                "model": {}, "rng": {"numpy": np.random.get_state()}}, path)
    return path


# (build(tmp_path) -> the call that must fail, exception, message pattern)
HOSTILE = [
    # -- data destroyed ------------------------------------------------------------------------
    pytest.param(lambda tmp: lambda: convert_script.main([str(_mvsec(tmp)), str(tmp / "indoor_flying1_data.hdf5"),
                                                          "--overwrite"]),
                 FileExistsError, r"indoor_flying1_data.hdf5: is the input recording", id="convert-output-is-input"),
    pytest.param(lambda tmp: (lambda src: (os.symlink(src, tmp / "link.h5"),
                                           lambda: convert_script.main([str(src), str(tmp / "link.h5"), "--overwrite"]))[1])(_mvsec(tmp)),
                 FileExistsError, r"link.h5: is the input recording", id="convert-output-symlinks-to-input"),
    pytest.param(lambda tmp: (lambda src: (os.link(src, tmp / "hard.h5"),
                                           lambda: convert_script.main([str(src), str(tmp / "hard.h5"), "--overwrite"]))[1])(_mvsec(tmp)),
                 FileExistsError, r"hard.h5: is the input recording", id="convert-output-hardlinks-to-input"),
    pytest.param(lambda tmp: (lambda src: ((tmp / "out.h5").write_text("keep me"),
                                           lambda: convert_script.main([str(src), str(tmp / "out.h5")]))[1])(_mvsec(tmp)),
                 FileExistsError, r"out.h5: exists; pass overwrite=True \(--overwrite\)", id="convert-existing-output"),
    pytest.param(lambda tmp: lambda: convert_recording(open_recording(_mvsec(tmp)), tmp / "o.h5", chunk_events=-1),
                 ValueError, r"chunk_events must be a positive integer.*-1", id="convert-chunk-events-negative"),
    pytest.param(lambda tmp: lambda: convert_recording(open_recording(_mvsec(tmp)), tmp / "o.h5", chunk_events=0),
                 ValueError, r"chunk_events must be a positive integer.*0", id="convert-chunk-events-zero"),
    pytest.param(lambda tmp: (lambda src: ((tmp / "folder").mkdir(),
                                           lambda: convert_script.main([str(src), str(tmp / "folder"), "--overwrite"]))[1])(_mvsec(tmp)),
                 IsADirectoryError, r"folder: is a folder; the output must be a file path", id="convert-output-is-folder"),
    # -- NaN timestamps --------------------------------------------------------------------------
    pytest.param(lambda tmp: lambda: HagenaarsReader(_hagenaars(tmp, -1)),
                 FormatError, r"seq.h5: field 'events/ts' is not a finite number at index 1999", id="hagenaars-nan-last-time"),
    pytest.param(lambda tmp: lambda: HagenaarsReader(_hagenaars(tmp, 1000)).events_range(0, 2000),
                 FormatError, r"seq.h5: field 'events/ts' is not a finite number at index 1000", id="hagenaars-nan-time"),
    pytest.param(lambda tmp: lambda: MVSECReader(_mvsec(tmp, nan_at=-1)),
                 FormatError, r"_data.hdf5: field '/davis/left/events column 2 \(t, seconds\)' is not a finite number at index 1999",
                 id="mvsec-nan-last-time"),
    pytest.param(lambda tmp: lambda: MVSECReader(_mvsec(tmp, nan_at=900)).events_range(0, 2000),
                 FormatError, r"_data.hdf5: field '/davis/left/events column 2 \(t, seconds\)' is not a finite number at index 900",
                 id="mvsec-nan-time"),
    pytest.param(lambda tmp: lambda: TextReader(_text(tmp, "nan 1 2 1")),
                 FormatError, r"events.txt: field 't' is not a finite number at index 2", id="text-nan-time"),
    # -- indexes trusted ---------------------------------------------------------------------------
    pytest.param(lambda tmp: lambda: H5Reader(_project(tmp, _set_ms_to_idx(lambda n: np.zeros(51, np.int64)))),
                 FormatError, r"rec.h5: dataset '/ms_to_idx' runs from 0 to 0, expected 0 to num_events = 3000",
                 id="h5-zeroed-ms-to-idx"),
    pytest.param(lambda tmp: lambda: H5Reader(_project(tmp, _set_ms_to_idx(lambda n: np.linspace(0, n, 20).astype(np.int64)))),
                 FormatError, r"rec.h5: dataset '/ms_to_idx' has shape \(20,\), expected \(51,\)", id="h5-short-ms-to-idx"),
    pytest.param(lambda tmp: lambda: H5Reader(_project(tmp, lambda f: f.attrs.__setitem__("t_end_us", 20_000))),
                 FormatError, r"rec.h5: events span \[\d+, \d+\] us, outside the attributes \[t_start_us, t_end_us\) = \[\d+, 20000\)",
                 id="h5-t-end-before-last-event"),
    pytest.param(lambda tmp: (lambda path: (lambda r: lambda: r.index_at(r.t_start + 31_500))(H5Reader(path)))(
                     _project(tmp, lambda f: f["ms_to_idx"].__setitem__(31, int(f["ms_to_idx"][31]) + 7))),
                 FormatError, r"rec.h5: dataset '/ms_to_idx' entry 31 = \d+ does not point at the first event",
                 id="h5-one-wrong-index-entry"),
    pytest.param(lambda tmp: lambda: DSECReader(_dsec(tmp, lambda f: f["ms_to_idx"].__setitem__(slice(None), 0))),
                 FormatError, r"events.h5: dataset '/ms_to_idx' entry \d+ = 0 is not the first event", id="dsec-zeroed-ms-to-idx"),
    pytest.param(lambda tmp: lambda: DSECReader(_dsec(tmp, lambda f: _cut(f, "ms_to_idx", 40))),
                 FormatError, r"events.h5: dataset '/ms_to_idx' has 40 entries but the events run to 99 ms; it is cut short",
                 id="dsec-short-ms-to-idx"),
    # -- formats ------------------------------------------------------------------------------------
    pytest.param(lambda tmp: (lambda path: (path.write_bytes(np.random.default_rng(1).bytes(500)),
                                            lambda: open_recording(path, "ecd-text"))[1])(tmp / "random.bin"),
                 FormatError, r"random.bin: line \d+ is not text", id="binary-forced-as-text"),
    pytest.param(lambda tmp: lambda: MVSECReader(_mvsec(tmp, x_value=-0.6)).events_range(0, 2000),
                 FormatError, r"_data.hdf5: field '/davis/left/events column 0 \(x\)' must hold whole, non-negative pixel "
                              r"coordinates; index 700 holds -0.6", id="mvsec-negative-fractional-x"),
    pytest.param(lambda tmp: lambda: TextReader(_text(tmp, "0.000300 10.7 2 1")),
                 FormatError, r"events.txt: field 'x' must hold whole, non-negative pixel coordinates; index 2 holds 10.7",
                 id="text-fractional-x"),
    # -- training recovery ---------------------------------------------------------------------------
    pytest.param(lambda tmp: (lambda run: lambda: train_script.main(["--resume", "--out", str(run), "--lr", "0.5",
                                                                      "--unroll", "2", "--no-progress", "--val-data", ""]))(_training_run(tmp)),
                 ValueError, r"changes the run's configuration \(lr: stored 0.0001, asked 0.5; unroll: stored 1, asked 2\); "
                             r"pass --allow-changes lr,unroll", id="resume-changed-config"),
    pytest.param(lambda tmp: (lambda run: lambda: train_script.main(["--resume", "--out", str(run), "--width", "8",
                                                                      "--allow-changes", "width"]))(_training_run(tmp)),
                 ValueError, r"--allow-changes width: a resume cannot change the network's shape", id="resume-allow-width"),
    pytest.param(lambda tmp: (lambda weights: lambda: train_script.main(["--resume", str(weights), "--out", str(tmp / "x")]))(_exported(tmp)),
                 ValueError, r"tiny.pt: a weights-only model file \(no optimizer, scheduler, rng\).*--init", id="resume-exported-weights"),
    pytest.param(lambda tmp: lambda: train_script.main(["--resume", "ev-mgrflownet-cpu-synthetic", "--out", str(tmp / "x")]),
                 ValueError, r"ev-mgrflownet-cpu-synthetic: is a shipped model.*--init ev-mgrflownet-cpu-synthetic",
                 id="resume-shipped-model-name"),
    # -- env options ------------------------------------------------------------------------------------
    pytest.param(lambda tmp: lambda: EventFlowEnv("synthetic-mini", flow_scaling=0),
                 ValueError, r"flow_scaling must be a positive finite number of pixels.*got 0", id="env-flow-scaling-0"),
    pytest.param(lambda tmp: lambda: EventFlowEnv("synthetic-mini", flow_limit=0),
                 ValueError, r"flow_limit must be a positive finite number of pixels.*got 0", id="env-flow-limit-0"),
    pytest.param(lambda tmp: lambda: EventFlowEnv("synthetic-mini", window_size=2.7),
                 ValueError, r"window_size must be a positive integer.*grid steps.*got 2.7", id="env-window-size-2.7"),
    *[pytest.param(lambda tmp, v=v: lambda: EventFlowEnv("synthetic-mini").reset(options={"sequence": v}),
                   ValueError, r"options\['sequence'\] must be a sequence name or an integer index in \[0, 3\), got",
                   id=f"env-sequence-{v!r}") for v in (True, 1.7, None, [0])],
    pytest.param(lambda tmp: lambda: EventFlowEnv("synthetic-mini").reset(
        options={"sequence": 0, "windows": [[60_000, 30_000]]}),
                 ValueError, r"options\['windows'\] row 0 = \[60000, 30000\]: t_end must be > t_start",
                 id="env-reversed-window"),
    # -- loading runs code ------------------------------------------------------------------------------
    pytest.param(lambda tmp: lambda: load_checkpoint(_pickled_code(tmp)),
                 CheckpointError, r"evil.pt: holds pickled Python objects", id="checkpoint-runs-code"),
    pytest.param(lambda tmp: lambda: load_checkpoint(_old_format(tmp)),
                 CheckpointError, r"old.pt: holds pickled Python objects.*export_model.py --upgrade .*old.pt", id="checkpoint-old-format"),
]


@pytest.mark.parametrize("build, error, message", HOSTILE)
def test_hostile_input_gets_a_clear_error(tmp_path, build, error, message):
    call = build(tmp_path)
    with pytest.raises(error, match=message):
        call()
    assert not (tmp_path / "code-ran").exists()  # nothing in a loaded file was executed


def _digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def test_convert_never_touches_the_input_or_an_existing_output(tmp_path):
    src = _mvsec(tmp_path)
    before = _digest(src)
    os.symlink(src, tmp_path / "link.h5")
    os.link(src, tmp_path / "hard.h5")
    for target in (src, tmp_path / "link.h5", tmp_path / "hard.h5"):
        with pytest.raises(FileExistsError, match="is the input recording"):
            convert_script.main([str(src), str(target), "--overwrite"])
    assert _digest(src) == before
    (tmp_path / "out.h5").write_text("keep me")
    with pytest.raises(FileExistsError):
        convert_script.main([str(src), str(tmp_path / "out.h5")])
    assert (tmp_path / "out.h5").read_text() == "keep me"
    convert_script.main([str(src), str(tmp_path / "out.h5"), "--overwrite"])  # asked for: replaced
    with H5Reader(tmp_path / "out.h5") as r:
        assert r.num_events == 2_000
    assert sorted(p.name for p in tmp_path.iterdir()) == ["hard.h5", "indoor_flying1_data.hdf5", "link.h5", "out.h5"]


def test_convert_chunk_events_option_is_checked(tmp_path, capsys):
    src = _mvsec(tmp_path)
    for bad in ("-1", "0", "many"):
        with pytest.raises(SystemExit):
            convert_script.main([str(src), str(tmp_path / "o.h5"), "--chunk-events", bad])
        assert f"--chunk-events: expected a positive integer, got {bad if bad == 'many' else int(bad)}".replace(
            "got many", "got 'many'") in capsys.readouterr().err
    assert not (tmp_path / "o.h5").exists()


def test_folder_output_leaves_no_temporary(tmp_path):
    src = _mvsec(tmp_path)
    (tmp_path / "folder").mkdir()
    with pytest.raises(IsADirectoryError):
        convert_recording(open_recording(src), tmp_path / "folder", overwrite=True)
    assert list((tmp_path / "folder").iterdir()) == [] and not list(tmp_path.glob("*.tmp-*"))


def _dead_pid() -> int:
    done = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    return int(done.stdout)


def test_temporaries_of_killed_writers_are_removed_by_the_next_run(tmp_path):
    src = _mvsec(tmp_path)
    dead, alive = _dead_pid(), os.getppid()  # a live process's temporary is a concurrent write: kept
    stale = tmp_path / f"out.h5.tmp-{dead}"
    live = tmp_path / f"out.h5.tmp-{alive}"
    stale.write_bytes(b"x" * 1000)
    live.write_bytes(b"y")
    convert_script.main([str(src), str(tmp_path / "out.h5")])
    assert not stale.exists() and live.exists() and (tmp_path / "out.h5").exists()
    # checkpoints: the next save (and the next training run's start) removes a killed save's temporary
    ckpt_stale = tmp_path / "run" / f"checkpoint.pt.tmp-{dead}"
    ckpt_stale.parent.mkdir()
    ckpt_stale.write_bytes(b"z" * 1000)
    save_checkpoint(tmp_path / "run" / "checkpoint.pt", {"model_name": "ev-flownet", "model_config": {}, "model": {}})
    assert not ckpt_stale.exists()


def test_h5_reader_accepts_its_own_files_and_checks_windows_cheaply(tmp_path):
    events = random_events(np.random.default_rng(0), 50_000, t_span=(0, 2_000_000))
    with H5Reader(write_h5(tmp_path / "ok.h5", events)) as r:
        for t in np.random.default_rng(1).integers(-10, 2_000_010, 200):
            assert r.index_at(int(t)) == np.searchsorted(events.t, t)


def test_checkpoints_round_trip_numpy_state_through_the_safe_loader(tmp_path):
    state = {"rng": np.random.default_rng(5).bit_generator.state, "bounds": np.arange(12, dtype=np.int64).reshape(3, 4),
             "names": np.array(["a", "bc"], object), "mask": np.array([True, False]), "n": np.int64(3)}
    path = save_checkpoint(tmp_path / "c.pt", {"model_name": "ev-flownet", "model_config": {}, "model": {}, "state": state})
    torch.load(path, weights_only=True)  # the file itself is in the safe schema
    back = load_checkpoint(path)["state"]
    assert back["rng"] == state["rng"] and back["n"] == 3 and back["names"].tolist() == ["a", "bc"]
    np.testing.assert_array_equal(back["bounds"], state["bounds"])
    assert back["bounds"].dtype == np.int64 and back["mask"].dtype == bool
    with pytest.raises(TypeError, match="checkpoint/state/f: a builtin_function_or_method cannot be saved safely"):
        save_checkpoint(tmp_path / "d.pt", {"model_name": "x", "model_config": {}, "model": {}, "state": {"f": len}})
    old = _old_format(tmp_path)
    upgrade_checkpoint(old)
    np.testing.assert_array_equal(load_checkpoint(old)["rng"]["numpy"][1], np.random.get_state()[1])


def test_shipped_weights_load_safely_as_float16():
    from agents.pretrained import WEIGHTS_DIR, list_pretrained

    names = list_pretrained()
    assert names
    for name in names:
        payload = torch.load(WEIGHTS_DIR / f"{name}.pt", weights_only=True)
        assert all(v.dtype == torch.float16 for v in payload["model"].values() if v.is_floating_point())


def test_cpu_runs_never_touch_cuda_rng(monkeypatch):
    """A CPU run on a machine with GPUs must neither initialise CUDA nor store every GPU's state."""
    def forbidden(*_args, **_kwargs):
        raise AssertionError("CUDA touched by a CPU run")

    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "get_rng_state_all", forbidden)
    monkeypatch.setattr(torch.cuda, "get_rng_state", forbidden)
    state = rng_state(torch.device("cpu"))
    assert "cuda" not in state


def test_distributed_setup_binds_each_rank_to_its_device(monkeypatch):
    import argparse

    calls = []
    monkeypatch.setenv("WORLD_SIZE", "2")
    monkeypatch.setenv("LOCAL_RANK", "1")
    monkeypatch.setattr(torch.cuda, "set_device", lambda index: calls.append(("set_device", index)))
    monkeypatch.setattr(train_script.dist, "init_process_group",
                        lambda backend, **kwargs: calls.append(("init", backend, str(kwargs.get("device_id")))))
    monkeypatch.setattr(train_script.dist, "get_rank", lambda: 1)
    args = argparse.Namespace(device="cuda")
    assert train_script.setup_distributed(args) == 1
    assert calls == [("set_device", 1), ("init", "nccl", "cuda:1")] and args.device == "cuda:1"
    calls.clear()
    args = argparse.Namespace(device="cpu")
    train_script.setup_distributed(args)
    assert calls == [("init", "gloo", "None")] and args.device == "cpu"


def test_resume_with_allowed_changes_uses_the_new_values(tmp_path):
    run = _training_run(tmp_path)
    train_script.main(["--resume", "--out", str(run), "--steps", "2", "--lr", "0.002", "--allow-changes", "lr",
                       "--no-progress", "--val-data", ""])
    payload = load_checkpoint(run / "checkpoint.pt")
    assert payload["step"] == 2 and payload["config"]["lr"] == 0.002
    assert payload["optimizer"]["param_groups"][0]["lr"] == pytest.approx(0.002)
