"""Hostile files, round three: nothing a checkpoint, a campaign file or an export name says may
run code or write outside what the user named. Each test first builds the attack as a hostile
user would (plain data that the safe loader accepts) and checks that no code ran."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

from agents.checkpoint import CheckpointError, load_model, save_checkpoint
from agents.registry import make_model
from tests.processes import holding

ROOT = Path(__file__).resolve().parents[1]


def _evil_checkpoint(path: Path, marker: Path, **extra) -> Path:
    """A checkpoint of plain data whose model name is a dotted path that, imported and called,
    writes ``marker`` (os.system would run a shell command the same way)."""
    payload = {"model_name": "os:system", "model_config": {"command": f"touch {marker}"}, "model": {}, **extra}
    save_checkpoint(path, payload)
    return path


def test_a_checkpoint_naming_a_dotted_path_runs_nothing(tmp_path):
    marker = tmp_path / "pwned"
    path = _evil_checkpoint(tmp_path / "evil.pt", marker)
    with pytest.raises(CheckpointError, match=r"evil\.pt.*plug-in model 'os:system'.*registered"):
        load_model(path)
    assert not marker.exists()


def test_a_plugin_checkpoint_loads_when_the_user_names_the_plugin(tmp_path, monkeypatch):
    monkeypatch.syspath_prepend(str(ROOT / "tests" / "plugin_example"))
    model = make_model("tiny_flow:build")
    path = save_checkpoint(tmp_path / "tiny.pt", {"model_name": "tiny_flow:build", "model_config": model.config,
                                                  "model": model.state_dict()})
    with pytest.raises(CheckpointError, match="plug-in model 'tiny_flow:build'"):
        load_model(path)
    loaded, _ = load_model(path, plugin="tiny_flow:build")
    for key, value in model.state_dict().items():
        assert torch.equal(loaded.state_dict()[key], value)
    with pytest.raises(CheckpointError, match="plug-in model"):  # naming another plug-in does not vouch for this one
        load_model(path, plugin="other_pkg:build")


def test_a_checkpoint_with_unknown_names_or_bad_config_is_refused(tmp_path):
    save_checkpoint(tmp_path / "a.pt", {"model_name": "no-such-model", "model_config": {}, "model": {}})
    with pytest.raises(CheckpointError, match="unknown model 'no-such-model'"):
        load_model(tmp_path / "a.pt")
    save_checkpoint(tmp_path / "b.pt", {"model_name": "ev-mgrflownet", "model_config": {"bogus": 1}, "model": {}})
    with pytest.raises(CheckpointError, match="cannot be built"):
        load_model(tmp_path / "b.pt")


@pytest.mark.parametrize("command", ["evaluate", "predict", "train"])
def test_commands_refuse_the_dotted_path_of_a_checkpoint(tmp_path, command):
    """evaluate.py --checkpoint, predict.py --model and train.py --resume on the planted file:
    a one-line error naming it, exit 2, and no code ran."""
    from tests.recordings import write_translating_recording

    marker = tmp_path / "pwned"
    import numpy as np

    recording = write_translating_recording(tmp_path / "rec.h5", np.random.default_rng(0))
    cfg = {"model": "os:system", "steps": 10}
    evil = _evil_checkpoint(tmp_path / "run" / "checkpoint.pt", marker, optimizer={}, scheduler={}, step=1,
                            config=cfg, rng={})
    argv = {"evaluate": ["--checkpoint", str(evil), "--data", str(recording), "--max-windows", "1", "--no-progress",
                         "--out", str(tmp_path / "eval")],
            "predict": [str(recording), "--model", str(evil), "--out", str(tmp_path / "f.h5"), "--no-video"],
            "train": ["--resume", str(evil), "--out", str(tmp_path / "run")]}[command]
    run = subprocess.run([sys.executable, str(ROOT / "scripts" / f"{command}.py"), *argv], capture_output=True,
                         text=True, cwd=ROOT, timeout=300)
    assert run.returncode == 2, run.stderr[-2000:]
    assert "os:system" in run.stderr and "Traceback" not in run.stderr, run.stderr[-2000:]
    assert not marker.exists()


def test_hub_and_pretrained_loader_refuse_a_planted_weights_file(tmp_path):
    from agents.pretrained import load_pretrained

    marker = tmp_path / "pwned"
    _evil_checkpoint(tmp_path / "planted.pt", marker)
    (tmp_path / "planted.json").write_text(json.dumps({"name": "planted"}))
    with pytest.raises(CheckpointError, match="plug-in model"):
        load_pretrained("planted", directory=tmp_path)
    assert not marker.exists()


def test_a_campaign_file_may_not_name_a_plugin_or_a_path(tmp_path):
    from evflow_cli.campaign import CampaignSpec

    good = {"name": "mine", "export": "ev-mgrflownet-cpu-mine", "train": ["--steps", "10"]}
    (tmp_path / "ok.json").write_text(json.dumps(good))
    assert CampaignSpec.read(tmp_path / "ok.json").export == "ev-mgrflownet-cpu-mine"
    for bad, message in [({"train": ["--model", "os:system"]}, "plug-in model 'os:system'"),
                         ({"train": ["--model=os:system"]}, "plug-in model 'os:system'"),
                         ({"export": "../../x"}, "campaign export '../../x'"),
                         ({"export": "a/b"}, "campaign export 'a/b'"),
                         ({"name": ".."}, "campaign name '..'")]:
        (tmp_path / "bad.json").write_text(json.dumps({**good, **bad}))
        with pytest.raises(ValueError, match=message.replace("(", r"\(")):
            CampaignSpec.read(tmp_path / "bad.json")


def test_export_validates_its_name_and_replaces_only_when_asked(tmp_path):
    from agents.pretrained import export_pretrained, list_pretrained

    model = make_model("ev-flownet", width="cpu")
    ckpt = save_checkpoint(tmp_path / "run" / "checkpoint.pt", {"model_name": "ev-flownet", "model_config": model.config,
                                                                "model": model.state_dict(), "step": 3, "config": {}})
    weights = tmp_path / "weights"
    for name in ("../../x", "a/b", "", "..", "UPPER"):
        with pytest.raises(ValueError, match="one file-name component"):
            export_pretrained(ckpt, name, {}, directory=weights)
    assert not (tmp_path / "x.pt").exists() and not weights.exists()
    export_pretrained(ckpt, "mine", {"note": "first"}, directory=weights)
    before = (weights / "mine.json").read_bytes()
    with pytest.raises(FileExistsError, match="mine.pt, mine.json.*--overwrite"):
        export_pretrained(ckpt, "mine", {"note": "second"}, directory=weights)
    assert (weights / "mine.json").read_bytes() == before
    export_pretrained(ckpt, "mine", {"note": "second"}, directory=weights, overwrite=True)
    assert json.loads((weights / "mine.json").read_text())["note"] == "second"
    assert list_pretrained(weights) == ["mine"]


def test_export_command_refuses_a_shipped_name_without_overwrite(tmp_path):
    from agents.pretrained import DEFAULT_PRETRAINED, WEIGHTS_DIR

    model = make_model("ev-flownet", width="cpu")
    ckpt = save_checkpoint(tmp_path / "checkpoint.pt", {"model_name": "ev-flownet", "model_config": model.config,
                                                        "model": model.state_dict(), "step": 3, "config": {}})
    shipped = (WEIGHTS_DIR / f"{DEFAULT_PRETRAINED}.pt").read_bytes()
    for name in (DEFAULT_PRETRAINED, "../../escaped"):
        run = subprocess.run([sys.executable, str(ROOT / "scripts" / "export_model.py"), str(ckpt), "--name", name],
                             capture_output=True, text=True, cwd=ROOT, timeout=120)
        assert run.returncode == 2, run.stderr[-2000:]
        assert "Traceback" not in run.stderr
    assert (WEIGHTS_DIR / f"{DEFAULT_PRETRAINED}.pt").read_bytes() == shipped
    assert not (ROOT.parent / "escaped.pt").exists()


def test_policy_refuses_an_unknown_input_read_from_a_file():
    from agents.policy import RecurrentPolicy

    with pytest.raises(ValueError, match="input_key must be one of"):
        RecurrentPolicy(make_model("ev-flownet", width="cpu"), input_key="__class__")


# -- outputs never follow a planted link; one writer per run folder --------------------------------------------------


def _train_argv(tmp_path: Path, out: Path, *extra) -> list[str]:
    import numpy as np

    from tests.recordings import write_translating_recording

    data = tmp_path / "dots.h5"
    if not data.exists():
        write_translating_recording(data, np.random.default_rng(3), sensor_size=(32, 32))
    return ["--data", str(data), "--width", "4", "--num-envs", "1", "--unroll", "1", "--steps", "1", "--out", str(out),
            "--val-data", "", "--no-progress", *extra]


def test_train_replaces_a_planted_config_link_instead_of_writing_through_it(tmp_path):
    from evflow_cli.commands import train as train_script

    victim = tmp_path / "recording.h5"
    victim.write_bytes(b"precious events" * 100)
    out = tmp_path / "run"
    out.mkdir()
    (out / "config.json").symlink_to(victim)
    train_script.main(_train_argv(tmp_path, out))
    assert victim.read_bytes() == b"precious events" * 100
    assert not (out / "config.json").is_symlink() and json.loads((out / "config.json").read_text())["steps"] == 1


def test_train_refuses_a_planted_metrics_link(tmp_path):
    from evflow_cli.commands import train as train_script

    victim = tmp_path / "notes.txt"
    victim.write_text("mine")
    out = tmp_path / "run"
    out.mkdir()
    (out / "metrics.jsonl").symlink_to(victim)
    with pytest.raises(FileExistsError, match=r"metrics.jsonl: is a symbolic link"):
        train_script.main(_train_argv(tmp_path, out, "--overwrite"))
    assert victim.read_text() == "mine"


def test_an_output_lock_planted_as_a_link_is_refused(tmp_path):
    from envs.outputs import Output

    victim = tmp_path / "recording.h5"
    victim.write_bytes(b"x" * 1000)
    (tmp_path / "flow.h5.lock").symlink_to(victim)
    with pytest.raises(FileExistsError, match="lock .* is a symbolic link"):
        Output(tmp_path / "flow.h5")
    assert victim.read_bytes() == b"x" * 1000


def test_atomic_writes_replace_a_link_and_never_follow_it(tmp_path):
    from envs.atomic import open_no_follow, write_atomic

    victim = tmp_path / "victim"
    victim.write_text("keep")
    (tmp_path / "a.json").symlink_to(victim)
    write_atomic(tmp_path / "a.json", "{}")
    assert victim.read_text() == "keep" and (tmp_path / "a.json").read_text() == "{}"
    (tmp_path / "b.log").symlink_to(victim)
    for mode in ("w", "a", "x"):
        with pytest.raises(FileExistsError, match="symbolic link"):
            open_no_follow(tmp_path / "b.log", mode)
    assert victim.read_text() == "keep"




def test_two_trainers_never_share_a_run_folder(tmp_path):
    from envs.outputs import folder_holder
    from evflow_cli.commands import train as train_script

    out = tmp_path / "run"
    with holding(out) as other:
        assert folder_holder(out) == other.pid
        with pytest.raises(FileExistsError, match=rf"another process \(pid {other.pid}\) is writing this folder"):
            train_script.main(_train_argv(tmp_path, out))
        assert not (out / "config.json").exists() and not (out / "metrics.jsonl").exists()
    assert folder_holder(out) is None  # killed: the kernel released its lock
    train_script.main(_train_argv(tmp_path, out))
    assert (out / "checkpoint.pt").exists()


def test_a_campaigns_trainer_dies_with_its_campaign(tmp_path):
    """kill -9 of the campaign: its child gets SIGTERM from the kernel (train.py saves and stops)."""
    code = ("import subprocess, sys, time\n"
            "from evflow_cli.commands.campaign import _die_with_parent\n"
            "child = subprocess.Popen([sys.executable, '-c', 'import time; time.sleep(120)'], preexec_fn=_die_with_parent)\n"
            "print(child.pid, flush=True)\n"
            "time.sleep(120)\n")
    parent = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True, cwd=ROOT)
    child = int(parent.stdout.readline())
    os.kill(parent.pid, signal.SIGKILL)
    parent.wait()
    deadline = time.time() + 20
    while time.time() < deadline:
        try:
            os.kill(child, 0)
        except ProcessLookupError:
            break
        time.sleep(0.1)
    else:
        os.kill(child, signal.SIGKILL)
        pytest.fail("the campaign's child outlived it")


# --- wrong input and users' faults (items 7 and 8): one clear line, nothing left behind ---------


def test_env_refuses_unknown_reset_options_copies_and_windows_longer_than_the_recording(tmp_path, rng):
    import copy
    import pickle

    from envs.env import EventFlowEnv
    from tests.recordings import write_translating_recording

    path = write_translating_recording(tmp_path / "dots.h5", rng, duration_us=200_000)
    env = EventFlowEnv(str(path))
    with pytest.raises(ValueError, match=r"reset options \['sequnce'\]: unknown"):
        env.reset(options={"sequnce": 0})
    for copier in (copy.deepcopy, pickle.dumps):
        with pytest.raises(TypeError, match="cannot be pickled or copied"):
            copier(env)
    too_long = EventFlowEnv(str(path), window="time", window_size=10**9)
    with pytest.raises(ValueError, match=r"'dots': a time window of 1000000000 us is longer than the whole recording"):
        too_long.reset()
    whole = EventFlowEnv(str(path), window="time", window_size=200_000)  # exactly the recording: one window
    _, info = whole.reset()
    assert (info["window"].t_start, info["window"].t_end) == (0, 200_000)


@pytest.mark.parametrize("argv, message", [
    (["predict.py", "{rec}", "--window", "time", "--window-size", "1000000000", "--out", "{out}/a/flow.h5"],
     "longer than the whole recording"),
    (["predict.py", "{rec}", "--device", "cuda", "--out", "{out}/a/flow.h5"], "--device: cuda"),
    (["train.py", "--device", "cuda:x", "--steps", "1", "--out", "{out}/a"], "expected a torch device"),
])
def test_users_faults_end_in_one_line_and_leave_no_folder(tmp_path, rng, argv, message):
    from tests.recordings import write_translating_recording

    if "cuda" in " ".join(argv) and torch.cuda.is_available() and "cuda:x" not in argv:
        pytest.skip("this machine has CUDA")
    rec = write_translating_recording(tmp_path / "dots.h5", rng, duration_us=150_000)
    out = tmp_path / "out"
    argv = [a.format(rec=rec, out=out) for a in argv]
    done = subprocess.run([sys.executable, str(ROOT / "scripts" / argv[0]), *argv[1:]], capture_output=True, text=True,
                          timeout=300, cwd=tmp_path)
    assert done.returncode == 2 and message in done.stderr and "Traceback" not in done.stderr, done.stderr[-2000:]
    assert not out.exists()  # no empty output folder either


@pytest.mark.parametrize("size", [(100_000, 100_000), (0, 346), (260, 16_385)])
def test_a_declared_sensor_size_is_checked_when_the_file_opens(tmp_path, rng, size):
    import h5py

    from envs.readers import open_recording
    from envs.readers.base import FormatError
    from tests.recordings import write_translating_recording

    path = write_translating_recording(tmp_path / "rec.h5", rng, duration_us=60_000)
    with h5py.File(path, "r+") as f:  # a hostile edit of the declared geometry only (a few bytes)
        f.attrs["sensor_height"], f.attrs["sensor_width"] = size
    with pytest.raises(FormatError, match=rf"rec\.h5: declares a {size[0]} x {size[1]} sensor"):
        open_recording(path)


def test_a_window_holding_more_events_than_its_bound_is_refused_before_it_is_read(monkeypatch):
    """Item 6: 10^7 events at one time stamp took 2.35 GB in one window; a window's events are
    bounded (envs.windows.MAX_WINDOW_EVENTS by default) and checked from the index, before the
    read, so a file's content cannot choose the memory."""
    import numpy as np

    from envs.env import EventFlowEnv
    from envs.readers.base import ArrayReader
    from envs.windows import MAX_WINDOW_EVENTS

    n = 60_000
    ev = np.zeros(n + 1, dtype=[("x", "<u2"), ("y", "<u2"), ("t", "<i8"), ("p", "i1")])
    ev["x"], ev["y"] = np.arange(n + 1) % 64, np.arange(n + 1) % 48
    ev["t"][:n], ev["t"][n] = 1000, 2000  # n events at one time stamp, one more at the end
    assert EventFlowEnv(ev, sensor_size=(48, 64), window="time", window_size=1000).max_window_events == MAX_WINDOW_EVENTS
    env = EventFlowEnv(ev, sensor_size=(48, 64), window="time", window_size=1000, max_window_events=50_000)
    reads = []
    original = ArrayReader.events_range
    monkeypatch.setattr(ArrayReader, "events_range", lambda self, *a: reads.append(a) or original(self, *a))
    with pytest.raises(ValueError, match=r"window 0 \(\[1000, 2000\) us\) of recording 'events' holds 60000 events, "
                                         r"more than the 50000"):
        env.reset()
    assert reads == []  # refused from the index, nothing read
    env = EventFlowEnv(ev, sensor_size=(48, 64), window="time", window_size=1000, max_window_events=None)
    _, info = env.reset()  # no bound: the user's choice
    assert len(info["window"].events) == n and reads == [(0, n)]
    with pytest.raises(ValueError, match="a count window of 80000 events holds 80000 events, more than the 50000"):
        EventFlowEnv(ev, sensor_size=(48, 64), window="count", window_size=80_000, max_window_events=50_000)
    with pytest.raises(ValueError, match="max_window_events must be a positive integer or None"):
        EventFlowEnv(ev, sensor_size=(48, 64), max_window_events=0)


# --- a full disk (item 5): one line, exit 3, the old outputs unchanged, no partial new one --------


def _full_disk(*args, **kwargs):
    import errno

    raise OSError(errno.ENOSPC, "No space left on device")


def test_a_full_disk_ends_convert_in_one_line_and_keeps_the_old_output(tmp_path, rng, monkeypatch, capsys):
    from envs.readers.h5 import H5Writer
    from evflow_cli.commands import convert
    from evflow_cli.commands.cli import run
    from tests.recordings import write_translating_recording

    rec = write_translating_recording(tmp_path / "rec.h5", rng, duration_us=100_000)
    out = tmp_path / "out" / "copy.h5"
    assert run(convert.main, [str(rec), str(out)]) == 0
    before = out.read_bytes()
    capsys.readouterr()
    monkeypatch.setattr(H5Writer, "append_events", _full_disk)
    assert run(convert.main, [str(rec), str(out), "--overwrite"]) == 3
    err = capsys.readouterr().err
    message = [line for line in err.splitlines() if line.startswith("error")]
    assert "Traceback" not in err and len(message) == 1 and message[0].startswith("error: the disk is full") and "run the command again" in message[0]
    assert out.read_bytes() == before and sorted(p.name for p in out.parent.iterdir()) == ["copy.h5"]
    monkeypatch.undo()
    assert run(convert.main, [str(rec), str(out), "--overwrite"]) == 0  # space freed: the rerun works


def test_a_full_disk_ends_training_in_one_line_and_keeps_the_checkpoint(tmp_path, monkeypatch, capsys):
    import agents.checkpoint
    from evflow_cli.commands import train
    from evflow_cli.commands.cli import run

    out = tmp_path / "run"
    argv = ["--model", "ev-flownet", "--width", "4", "--data", "synthetic-mini", "--crop", "32", "32", "--num-envs", "1",
            "--unroll", "2", "--no-progress", "--val-data", "", "--out", str(out)]
    assert run(train.main, [*argv, "--steps", "1"]) in (0, None)
    before = (out / "checkpoint.pt").read_bytes()
    real = agents.checkpoint.torch.save
    monkeypatch.setattr(agents.checkpoint.torch, "save", _full_disk)
    assert run(train.main, [*argv, "--steps", "2", "--resume"]) == 3
    assert capsys.readouterr().err.strip().splitlines()[-1].startswith("error: the disk is full")
    assert (out / "checkpoint.pt").read_bytes() == before and not list(out.glob("*.tmp-*"))
    monkeypatch.setattr(agents.checkpoint.torch, "save", real)
    assert run(train.main, [*argv, "--steps", "2", "--resume"]) in (0, None)


def test_an_envs_window_in_a_checkpoint_is_saved_as_its_events_and_bounds(tmp_path):
    """The learner's checkpoint holds the env's last info, whose "window" is a Window (not a dict
    since the window became a type): the safe schema stores its events and bounds, as it stored
    the window dict before, and loads them back equal."""
    import numpy as np

    from agents.checkpoint import load_checkpoint
    from envs.events import Events
    from envs.windows import Window

    events = Events.create(np.array([1, 2, 3]), np.array([0, 1, 2]), np.array([10, 20, 30]), np.array([1, -1, 1]),
                           (4, 5))
    window = Window.of(events, 5, 35)
    path = save_checkpoint(tmp_path / "c.pt", {"model_name": "ev-flownet", "model_config": {}, "model": {},
                                               "info": {"final_info": {"window": [window, None]}}})
    saved = load_checkpoint(path)["info"]["final_info"]["window"][0]
    assert (saved["t_start"], saved["t_end"]) == (5, 35)
    for key in ("x", "y", "t", "p"):
        np.testing.assert_array_equal(saved[key], getattr(events, key))
