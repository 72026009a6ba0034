"""Hostile input: files that are corrupt, contradictory or aimed at the user's data, and commands
that would lose work. Each row of ``HOSTILE`` builds one such case and names the error it must
raise (a clear message naming the file or option, the bad value and what was expected); the
tests after the table check what must survive (the user's files, no temporaries)."""

from __future__ import annotations

import hashlib
import json
import os
import pickle
import re
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest
import torch

from agents.checkpoint import CheckpointError, load_checkpoint, rng_state, save_checkpoint, upgrade_checkpoint
from envs.atomic import host_name
from envs.env import EventFlowEnv
from envs.readers import FormatError, H5Reader, open_recording, write_h5
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
from envs.readers.prophesee import PropheseeDatReader  # noqa: E402
from evflow_cli.commands import convert as convert_script  # noqa: E402
from evflow_cli.commands import evaluate as evaluate_script  # noqa: E402
from evflow_cli.commands import predict as predict_script  # noqa: E402
from evflow_cli.commands import train as train_script  # noqa: E402
from tests.test_prophesee import dat_bytes, evt2_words, raw_header, sorted_events  # noqa: E402


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


def _recording(tmp: Path) -> Path:
    """A small project h5 recording with ground truth every 30 ms (32 x 32 pixels, 300 ms)."""
    return write_translating_recording(tmp / "rec.h5", np.random.default_rng(3), sensor_size=(32, 32))


def _predict_call(tmp: Path, *extra: str, rec: Path | None = None):
    """scripts/predict.py on :func:`_recording` with a small untrained network, writing q.h5;
    ``extra`` may name the recording as ``{rec}``."""
    rec = rec or _recording(tmp)
    argv = [str(rec), "--model", "ev-mgrflownet", "--width", "4", "--out", str(tmp / "q.h5"), "--no-progress",
            "--window", "time", "--window-size", "30000", *(a.format(rec=rec) for a in extra)]
    return lambda: predict_script.main(argv)


def _evaluate_call(tmp: Path, *extra: str, rec: Path | None = None):
    rec = rec or _recording(tmp)
    argv = ["--model", "ev-mgrflownet", "--width", "4", "--data", str(rec), "--dt", "1", "--max-windows", "2",
            "--pictures", "0", "--no-progress", "--out", str(tmp / "ev"), *(a.format(rec=rec) for a in extra)]
    return lambda: evaluate_script.main(argv)


def _kept(path: Path, text: str = "keep me") -> Path:
    path.write_text(text)
    return path


def _raw(tmp: Path, header: bytes | None = None, name: str = "cam.raw") -> Path:
    """An EVT 2.0 file of a 260 x 346 camera (DAVIS346 geometry) whose events reach x = 345."""
    x, y, t, p = sorted_events(np.random.default_rng(2), 2_000, (260, 346), 0, 100_000)
    x[-1], y[-1] = 345, 259
    path = tmp / name
    path.write_bytes((header or raw_header("EVT2", (260, 346))) + evt2_words(x, y, t, p).astype("<u4").tobytes())
    return path


def _cached_raw(tmp: Path) -> Path:
    """:func:`_raw`, opened once at its header's geometry, so its time index is cached."""
    path = _raw(tmp)
    open_recording(path).close()
    return path


def _dat(tmp: Path, t: np.ndarray, name: str = "rec.dat") -> Path:
    n = len(t)
    x, y = np.arange(n) % 640, np.arange(n) % 480
    path = tmp / name
    path.write_bytes(dat_bytes(x, y, np.asarray(t, np.int64), np.arange(n) % 2))
    return path


def _spiked_dat_times(n: int = 1_000, at: int = 500) -> np.ndarray:
    """Sorted times with one record stamped 0xFFFFFFF0 (a corrupt record, not a wrap)."""
    t = 10_000 + 100 * np.arange(n, dtype=np.int64)
    t[at] = 0xFFFFFFF0
    return t


def _with_ground_truth_1e30(tmp: Path) -> Path:
    path = _recording(tmp)
    with h5py.File(path, "a") as f:
        f["flow/flow"][0, 0, 5, 7] = 1e30
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
    # -- issue 41 (1): every output guarded, the input above all ---------------------------------
    pytest.param(lambda tmp: _predict_call(tmp, "--video", "{rec}"),
                 FileExistsError, r"rec.h5: is the input recording", id="predict-video-is-input"),
    pytest.param(lambda tmp: _predict_call(tmp, "--json", "{rec}"),
                 FileExistsError, r"--json .*rec.h5: is the input recording", id="predict-json-is-input"),
    pytest.param(lambda tmp: _evaluate_call(tmp, "--json", "{rec}"),
                 FileExistsError, r"--json .*rec.h5: is the input recording", id="evaluate-json-is-input"),
    pytest.param(lambda tmp: _predict_call(tmp, "--video", str(_kept(tmp / "notes.gif"))),
                 FileExistsError, r"notes.gif: exists; pass overwrite=True \(--overwrite\)", id="predict-existing-video"),
    pytest.param(lambda tmp: _predict_call(tmp, "--json", str(_kept(tmp / "res.json"))),
                 FileExistsError, r"--json .*res.json: exists; pass overwrite=True", id="predict-existing-json"),
    pytest.param(lambda tmp: _evaluate_call(tmp, "--json", str(_kept(tmp / "res.json"))),
                 FileExistsError, r"--json .*res.json: exists; pass overwrite=True", id="evaluate-existing-json"),
    pytest.param(lambda tmp: _predict_call(tmp, "--json", str(tmp / "q.h5")),
                 FileExistsError, r"q.h5: is also --json .*q.h5 of this command", id="predict-json-is-out"),
    # -- (2) a new training run in a used run folder ------------------------------------------------
    pytest.param(lambda tmp: (lambda run: lambda: train_script.main(
        ["--data", str(tmp / "dots.h5"), "--width", "4", "--num-envs", "1", "--unroll", "1", "--steps", "1",
         "--out", str(run), "--val-data", "", "--no-progress"]))(_training_run(tmp)),
                 FileExistsError, r"--out .*run: holds an earlier run \(checkpoint.pt, metrics.jsonl\); continue it with "
                                  r"--resume, start afresh with --overwrite", id="train-used-run-folder"),
    # -- (4) a cached Prophesee time index still checks the geometry -----------------------------------
    pytest.param(lambda tmp: (lambda path: lambda: open_recording(path, sensor_size=(346, 260)))(_cached_raw(tmp)),
                 FormatError, r"cam.raw: event x=345 outside the 346x260 sensor", id="prophesee-cached-index-transposed"),
    pytest.param(lambda tmp: (lambda path: lambda: open_recording(path, sensor_size=(100, 100)))(_cached_raw(tmp)),
                 FormatError, r"cam.raw: event x=\d+ outside the 100x100 sensor", id="prophesee-cached-index-100x100"),
    pytest.param(lambda tmp: (lambda path: lambda: convert_script.main([str(path), str(tmp / "o.h5"), "--sensor-size", "346",
                                                                         "260"]))(_cached_raw(tmp)),
                 FormatError, r"cam.raw: event x=345 outside the 346x260 sensor", id="convert-prophesee-transposed"),
    # -- (5) DAT times going backwards are no wraps ----------------------------------------------------------
    pytest.param(lambda tmp: lambda: PropheseeDatReader(_dat(tmp, 1_000_000 - 100 * np.arange(1_000))),
                 FormatError, r"rec.dat: the event at byte \d+ is stamped \d+ us \(0x[0-9A-F]{8}\), \d+ us before an event ahead of it",
                 id="dat-reversed-records"),
    pytest.param(lambda tmp: lambda: PropheseeDatReader(_dat(tmp, _spiked_dat_times())),
                 FormatError, r"rec.dat: the event at byte \d+ is stamped 4294967280 us \(0xFFFFFFF0\), 59916 us before an event ahead",
                 id="dat-one-record-at-0xFFFFFFF0"),
    pytest.param(lambda tmp: lambda: convert_script.main([str(_dat(tmp, 1_000_000 - 100 * np.arange(1_000))),
                                                          str(tmp / "o.h5")]),
                 FormatError, r"rec.dat: the event at byte \d+ is stamped", id="convert-dat-reversed-records"),
    # -- (6) ECD text values checked ------------------------------------------------------------------------
    pytest.param(lambda tmp: lambda: TextReader(_text(tmp, "0.000300 70000 2 1")),
                 FormatError, r"events.txt: line 3 \(event 2\): x = 70000 is beyond the largest sensor side, 16384",
                 id="text-x-70000"),
    pytest.param(lambda tmp: lambda: TextReader(_text(tmp, "0.000300 1e10 2 1")),
                 FormatError, r"events.txt: line 3 \(event 2\): x = 10000000000 is beyond the largest sensor side",
                 id="text-x-1e10"),
    pytest.param(lambda tmp: lambda: TextReader(_text(tmp, "1e12 1 2 1")),
                 FormatError, r"events.txt: line 3 \(event 2\): t = 1000000000000.0 s is more than 86400 s \(24 h\) after "
                              r"the first event's", id="text-t-1e12"),
    pytest.param(lambda tmp: lambda: TextReader(_text(tmp, "1e300 1 2 1")),
                 FormatError, r"events.txt: line 3 \(event 2\): t = 1e\+300 s is more than", id="text-t-1e300"),
    pytest.param(lambda tmp: lambda: TextReader(_text(tmp, "0.000300 1 2 0.5")),
                 FormatError, r"events.txt: line 3 \(event 2\): polarity p = 0.5; expected 0 or 1", id="text-p-0.5"),
    # -- (7) header values that do not parse name the file ------------------------------------------------------
    pytest.param(lambda tmp: lambda: open_recording(_raw(tmp, b"% evt 2.0\n% format EVT2;height=abc;width=346\n% end\n")),
                 FormatError, r"cam.raw: the header's '% format EVT2;height=abc;width=346' gives height 'abc'",
                 id="raw-header-height-abc"),
    pytest.param(lambda tmp: (lambda path: (path.write_bytes(dat_bytes(np.arange(3), np.arange(3), np.arange(3), np.ones(3))
                                                             .replace(b"% Width 640", b"% Width abc")),
                                            lambda: PropheseeDatReader(path))[1])(tmp / "w.dat"),
                 FormatError, r"w.dat: the header's '% Height' / '% Width' lines gives height '480' and width 'abc'",
                 id="dat-header-width-abc"),
    # -- (8) ground truth bounded by the sensor ------------------------------------------------------------------
    pytest.param(lambda tmp: (lambda path: lambda: EventFlowEnv(str(path)).reset())(_with_ground_truth_1e30(tmp)),
                 FormatError, r"rec.h5 \(window \[0, 30000\) us\): ground-truth flow at pixel \(x=7, y=5\) is "
                              r"\(1e\+30, -3\) px; a valid pixel must hold a finite displacement of at most 128 px",
                 id="ground-truth-1e30"),
    pytest.param(lambda tmp: lambda: write_h5(tmp / "gt.h5", random_events(np.random.default_rng(0), 100, (8, 8)),
                                              flows=[(0, 1000, np.full((2, 8, 8), np.nan, np.float32), None)]),
                 FormatError, r"gt.h5 \(flow over \[0, 1000\) us\): ground-truth flow at pixel \(x=0, y=0\) is \(nan",
                 id="ground-truth-nan-written"),
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


# -- issue 41: what must survive, and how the commands answer ------------------------------------


def test_outputs_never_replace_the_input_and_replace_a_file_only_when_asked(tmp_path):
    """(1) predict and evaluate: the recording survives every output option aimed at it, an
    existing video or JSON survives unless --overwrite, and nothing is left half-written."""
    rec = _recording(tmp_path)
    before = _digest(rec)
    for extra in (["--video", str(rec)], ["--json", str(rec)], ["--out", str(rec)]):
        for overwrite in ([], ["--overwrite"]):
            with pytest.raises(FileExistsError, match="is the input recording"):
                _predict_call(tmp_path, *extra, *overwrite, rec=rec)()
    with pytest.raises(FileExistsError, match="is the input recording"):
        _evaluate_call(tmp_path, "--json", str(rec), "--overwrite", rec=rec)()
    assert _digest(rec) == before
    notes, res = _kept(tmp_path / "notes.gif"), _kept(tmp_path / "res.json")
    for extra in (["--video", str(notes)], ["--json", str(res)]):
        with pytest.raises(FileExistsError, match="exists; pass overwrite=True"):
            _predict_call(tmp_path, *extra, rec=rec)()
    assert notes.read_text() == res.read_text() == "keep me" and not (tmp_path / "q.h5").exists()
    _predict_call(tmp_path, "--video", str(notes), "--json", str(res), "--overwrite", rec=rec)()  # asked for: replaced
    assert notes.read_bytes()[:3] == b"GIF" and json.loads(res.read_text())["windows"] == 10
    assert not list(tmp_path.glob("*.tmp-*")) and not list(tmp_path.glob("*.lock"))


def test_a_new_run_in_a_used_folder_starts_afresh_only_when_asked(tmp_path):
    """(2) the refused run leaves the earlier run as it was; --overwrite logs steps 1, 2 once."""
    run = _training_run(tmp_path)
    before = (_digest(run / "checkpoint.pt"), (run / "metrics.jsonl").read_text())
    common = ["--data", str(tmp_path / "dots.h5"), "--width", "4", "--num-envs", "1", "--unroll", "1", "--out", str(run),
              "--val-data", "", "--no-progress"]
    with pytest.raises(FileExistsError, match="holds an earlier run"):
        train_script.main([*common, "--steps", "2"])
    assert (_digest(run / "checkpoint.pt"), (run / "metrics.jsonl").read_text()) == before
    train_script.main([*common, "--steps", "2", "--overwrite"])
    steps = [json.loads(line)["step"] for line in (run / "metrics.jsonl").read_text().splitlines()]
    assert steps == [1, 2]


def _holder(path: Path) -> subprocess.Popen:
    """Another process that claims ``path`` as its output and holds it until its stdin closes."""
    code = ("import sys; from envs.outputs import Output; o = Output(sys.argv[1]); print('ready', flush=True); "
            "sys.stdin.read()")
    proc = subprocess.Popen([sys.executable, "-c", code, str(path)], cwd=ROOT, stdin=subprocess.PIPE,
                            stdout=subprocess.PIPE, text=True)
    assert proc.stdout.readline().strip() == "ready"
    return proc


def test_a_second_writer_fails_naming_the_first(tmp_path):
    """(3) while one process writes out.h5 another fails naming it; once it is done (or killed:
    the kernel drops its lock) the next writer goes ahead."""
    src, rec = _mvsec(tmp_path), _recording(tmp_path)
    out = tmp_path / "out.h5"
    first = _holder(out)
    try:
        with pytest.raises(FileExistsError, match=rf"out.h5: another process \(pid {first.pid}\) is writing it now, "
                                                  rf"to out.h5.tmp-{re.escape(host_name())}-{first.pid}"):
            convert_script.main([str(src), str(out)])
        with pytest.raises(FileExistsError, match=rf"another process \(pid {first.pid}\)"):
            predict_script.main([str(rec), "--model", "ev-mgrflownet", "--width", "4", "--out", str(out), "--no-video",
                                 "--no-progress"])
    finally:
        first.kill()
        first.wait()
    assert not out.exists()
    convert_script.main([str(src), str(out)])  # the killed holder's lock is no obstacle
    with H5Reader(out) as r:
        assert r.num_events == 2_000
    assert not list(tmp_path.glob("out.h5.*"))


def test_dat_backward_time_names_the_byte_offset_and_real_wraps_still_read(tmp_path):
    """(5) the corrupt record's own offset, not a 2^32 us shift of every later event."""
    path = _dat(tmp_path, _spiked_dat_times(at=500))
    header = path.read_bytes().index(bytes([0x0C, 8])) + 2
    with pytest.raises(FormatError, match=rf"rec.dat: the event at byte {header + 500 * 8} is stamped 4294967280 us"):
        PropheseeDatReader(path, chunk_words=97, index_dir=tmp_path / "index")
    late = 10_000 + 100 * np.arange(50, dtype=np.int64)
    late[20] -= 150  # a few hundred us early: a late-stamped event, given the time before it
    with pytest.warns(UserWarning, match="1 events were stamped earlier"):
        r = PropheseeDatReader(_dat(tmp_path, late, "late.dat"), index_dir=tmp_path / "index")
    with r:
        assert r.reordered_events == 1 and r.t_end == late[-1] + 1
    wrap = (1 << 32) - 5_000 + 100 * np.arange(100, dtype=np.int64)  # crosses 2^32 once
    with PropheseeDatReader(_dat(tmp_path, wrap, "wrap.dat"), chunk_words=7, index_dir=tmp_path / "index") as r:
        np.testing.assert_array_equal(r.events_range(0, 100).t, wrap)


def test_text_with_a_byte_order_mark_keeps_its_first_event(tmp_path):
    """(6) a UTF-8 BOM before the first event line (Windows editors) is skipped, not the event."""
    path = tmp_path / "events.txt"
    path.write_bytes(b"\xef\xbb\xbf0.000100 3 4 1\n0.000200 5 6 0\n0.000300 7 8 1\n")
    with TextReader(path) as r:
        ev = r.events_range(0, r.num_events)
        assert r.num_events == 3 and ev.t.tolist() == [100, 200, 300] and ev.x.tolist() == [3, 5, 7]
    path.write_bytes(b"\xef\xbb\xbf# a header\n0.000100 3 4 1\n0.000200 5 6 0\n")
    with TextReader(path) as r:
        assert r.num_events == 2 and r.time_of(0) == 100


@pytest.mark.parametrize("command, argv, message", [
    ("evaluate", ["--dt-ratio", "0"], "argument --dt-ratio: expected a finite number > 0, got 0.0"),
    ("evaluate", ["--dt-ratio", "-1"], "argument --dt-ratio: expected a finite number > 0, got -1.0"),
    ("evaluate", ["--dt-ratio", "nan"], "argument --dt-ratio: expected a finite number > 0, got nan"),
    ("evaluate", ["--max-windows", "0"], "argument --max-windows: expected a positive integer, got 0"),
    ("evaluate", ["--max-windows", "-2"], "argument --max-windows: expected a positive integer, got -2"),
    ("train", ["--steps", "-3"], "argument --steps: expected an integer >= 0, got -3"),
    ("train", ["--lr", "inf"], "argument --lr: expected a finite number >= 0, got inf"),
    ("predict", ["--start", "nan"], "argument --start: expected a finite number >= 0, got nan"),
    ("predict", ["--fps", "0"], "argument --fps: expected a finite number > 0, got 0.0"),
    ("convert", ["--flow-dt", "0"], "argument --flow-dt: expected a positive integer, got 0"),
])
def test_numeric_options_are_checked_when_parsed(tmp_path, capsys, command, argv, message):
    """(7) a bad number stops the command before it reads or writes anything, naming the option
    and the accepted range."""
    rec = _recording(tmp_path)
    out = tmp_path / "out"
    full = {
        "evaluate": lambda: _evaluate_call(tmp_path, *argv, rec=rec),
        "train": lambda: lambda: train_script.main(["--data", str(rec), "--width", "4", "--num-envs", "1", "--unroll", "1",
                                                    "--out", str(out), "--val-data", "", "--no-progress", *argv]),
        "predict": lambda: _predict_call(tmp_path, *argv, rec=rec),
        "convert": lambda: lambda: convert_script.main([str(rec), str(out / "c.h5"), *argv]),
    }[command]()
    with pytest.raises(SystemExit) as stop:
        full()
    assert stop.value.code == 2 and message in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["rec.h5"]  # nothing written


def test_unwritable_outputs_are_found_before_any_work(tmp_path):
    """(7) a --video or --json that cannot be written fails before the run: no flow file, no
    summary lost after an hour of work."""
    rec = _recording(tmp_path)
    blocker = _kept(tmp_path / "file.txt")
    for option in ("--video", "--json"):
        with pytest.raises(NotADirectoryError, match=r"file.txt/x/v.gif: cannot create its folder .*file.txt/x: Not a dir"):
            _predict_call(tmp_path, option, str(blocker / "x" / "v.gif"), rec=rec)()
        assert not (tmp_path / "q.h5").exists()
    with pytest.raises(NotADirectoryError, match=r"--out .*file.txt/ev/table.md: cannot create its folder"):
        evaluate_script.main(["--zero", "--data", str(rec), "--out", str(blocker / "ev"), "--no-progress"])


def test_user_errors_print_one_line_and_exit_2(tmp_path):
    """(9) scripts/*.py: ``error: <message>`` and status 2 for a user error, the traceback with
    EVFLOW_DEBUG=1; an unexpected exception keeps its traceback."""
    from evflow_cli.commands.cli import run

    missing = tmp_path / "missing.h5"
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    done = subprocess.run([sys.executable, str(ROOT / "scripts" / "convert.py"), str(missing), str(tmp_path / "o.h5")],
                          capture_output=True, text=True, env={**env, "EVFLOW_DEBUG": "0"})
    assert done.returncode == 2 and done.stderr == f"error: {missing}: no such file or folder\n"
    done = subprocess.run([sys.executable, str(ROOT / "scripts" / "convert.py"), str(missing), str(tmp_path / "o.h5")],
                          capture_output=True, text=True, env={**env, "EVFLOW_DEBUG": "1"})
    assert done.returncode == 1 and "Traceback" in done.stderr and "no such file or folder" in done.stderr
    # in process: the same for every command, argparse's own errors untouched
    rec = _recording(tmp_path)
    _kept(tmp_path / "res.json")
    assert run(evaluate_script.main, ["--zero", "--data", str(rec), "--json", str(tmp_path / "res.json"),
                                      "--out", str(tmp_path / "ev")]) == 2

    def numpy_fails(argv):  # a bug, not a user error: raised inside numpy, not by a raise of ours
        return np.zeros(3).reshape(2, 2)

    with pytest.raises(ValueError, match="cannot reshape"):
        run(numpy_fails)
