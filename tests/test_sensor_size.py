"""``--sensor-size`` on every command that opens a recording: Prophesee files whose header gives
no geometry (EVT 2.0, EVT 3.0, DAT; older cameras and converters write none) are read whole when
it is given, refused without it by a message naming the option, and ``auto`` picks the smallest
known sensor holding every event (envs.readers._common.KNOWN_SENSORS), with a warning."""

from __future__ import annotations

import json
from pathlib import Path

import h5py
import numpy as np
import pytest

from envs.readers import H5Reader, open_recording
from envs.readers._common import auto_sensor_size
from evflow_cli.commands import cli
from evflow_cli.commands import convert as convert_command
from evflow_cli.commands import evaluate as evaluate_command
from evflow_cli.commands import predict as predict_command
from evflow_cli.commands import train as train_command
from tests.test_prophesee import assert_events, dat_bytes, evt2_words, evt3_words, sorted_events, write

SENSOR = (48, 64)  # (height, width) of the recordings below; no file says it
FORMATS = ("evt2", "evt3", "dat")


def write_without_geometry(folder: Path, fmt: str, x, y, t, p) -> Path:
    """A RAW (EVT 2.0 / 3.0) or DAT file of these events whose header names no sensor size."""
    if fmt == "evt2":
        return write(folder / "cam2.raw", b"% evt 2.0\n% end\n", evt2_words(x, y, t, p))
    if fmt == "evt3":
        return write(folder / "cam3.raw", b"% evt 3.0\n% end\n", evt3_words(x, y, t, p)[0])
    path = folder / "cam.dat"
    with_geometry = dat_bytes(x, y, t, p, sensor=(1, 1))  # the header lines are dropped below
    path.write_bytes(with_geometry.replace(b"% Width 1\n% Height 1\n", b""))
    assert b"Width" not in path.read_bytes()[:200]
    return path


@pytest.fixture(scope="module")
def events():
    return sorted_events(np.random.default_rng(7), 3000, SENSOR, 1_000, 200_000)


@pytest.fixture
def recording(tmp_path, events, request):
    return write_without_geometry(tmp_path, request.param, *events)


def command_line(command: str, recording: Path, out: Path) -> tuple:
    """(main, argv) of a short run of ``command`` on ``recording``, writing under ``out``."""
    time_windows = ["--window", "time", "--window-size", "50000"]
    if command == "convert":
        return convert_command.main, [str(recording), str(out / "rec.h5")]
    if command == "predict":
        return predict_command.main, [str(recording), "--model", "plugin_example.tiny_flow:build", "--out",
                                      str(out / "flow.h5"), "--no-video", "--no-progress", *time_windows]
    if command == "evaluate":
        return evaluate_command.main, ["--zero", "--data", str(recording), "--out", str(out / "eval"),
                                       "--pictures", "0", "--no-progress", *time_windows]
    return train_command.main, ["--data", str(recording), "--width", "4", "--num-envs", "1", "--unroll", "2",
                                "--steps", "1", "--device", "cpu", "--out", str(out / "run"), "--val-data", "",
                                "--no-progress", *time_windows]


@pytest.fixture
def plugin_path(monkeypatch):
    monkeypatch.syspath_prepend(str(Path(__file__).parent))


@pytest.mark.parametrize("recording", FORMATS, indirect=True)
@pytest.mark.parametrize("command", ["convert", "predict", "evaluate", "train"])
def test_each_command_reads_a_file_without_geometry_given_the_size(recording, command, events, tmp_path, plugin_path):
    main, argv = command_line(command, recording, tmp_path)
    assert cli.run(main, argv + ["--sensor-size", str(SENSOR[0]), str(SENSOR[1])]) == 0
    if command == "convert":
        with H5Reader(tmp_path / "rec.h5") as h5:
            assert h5.sensor_size == SENSOR
            assert_events(h5.events_range(0, h5.num_events), *events)
    elif command == "predict":
        with h5py.File(tmp_path / "flow.h5", "r") as f:
            assert tuple(f.attrs["sensor_size"]) == SENSOR and f["flow"].shape[-2:] == SENSOR
            assert f["num_events"][:].sum() == len(events[2])  # every event, in 50 ms windows
    elif command == "evaluate":
        results = json.loads((tmp_path / "eval" / "results.json").read_text())
        assert results["overall"]["time"]["windows"] >= 3 and results["overall"]["time"]["hmc"] > 0
    else:
        assert json.loads((tmp_path / "run" / "config.json").read_text())["sensor_size"] == list(SENSOR)
        assert (tmp_path / "run" / "checkpoint.pt").exists()


@pytest.mark.parametrize("recording", FORMATS, indirect=True)
@pytest.mark.parametrize("command", ["convert", "predict", "evaluate", "train"])
def test_each_command_refuses_a_file_without_geometry_naming_the_option(recording, command, tmp_path, plugin_path,
                                                                         capsys):
    main, argv = command_line(command, recording, tmp_path)
    assert cli.run(main, argv) == 2
    message = capsys.readouterr().err.strip().splitlines()[-1]
    assert message.startswith(f"error: {recording}: the ")
    assert "--sensor-size H W" in message and "data_options={'sensor_size'" in message  # the CLI's and the env's way


@pytest.mark.parametrize("recording", FORMATS, indirect=True)
def test_auto_picks_the_smallest_known_sensor_holding_the_events_and_warns(recording, tmp_path):
    with pytest.warns(UserWarning, match=r"sensor_size auto: 180x240 \(height x width; DAVIS240"):
        with open_recording(recording, sensor_size="auto") as reader:
            assert reader.sensor_size == (180, 240)


def test_auto_takes_the_header_geometry_where_there_is_one(tmp_path, events):
    import warnings

    from tests.test_prophesee import raw_header

    path = write(tmp_path / "hd.raw", raw_header("EVT2", (720, 1280)), evt2_words(*events))
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no guess, so no warning
        with open_recording(path, sensor_size="auto") as reader:
            assert reader.sensor_size == (720, 1280)


def test_auto_on_the_command_line(tmp_path):
    x, y, t, p = sorted_events(np.random.default_rng(1), 2000, (250, 330), 0, 100_000)  # wider than 320
    x[-1], y[-1] = 329, 249  # the events reach these: DAVIS346 (260 x 346) is the smallest that holds them
    recording = write_without_geometry(tmp_path, "evt3", x, y, t, p)
    with pytest.warns(UserWarning, match=r"260x346 \(height x width; DAVIS346.*x <= 329, y <= 249"):
        assert cli.run(convert_command.main, [str(recording), str(tmp_path / "rec.h5"), "--sensor-size", "auto"]) == 0
    with H5Reader(tmp_path / "rec.h5") as h5:
        assert h5.sensor_size == (260, 346)


def test_auto_on_a_text_file_without_a_size_line(tmp_path):
    path = tmp_path / "events.txt"
    path.write_text("0.001 10 5 1\n0.002 300 200 0\n0.003 2 250 1\n")
    with pytest.warns(UserWarning, match=r"260x346 \(height x width; DAVIS346"):
        with open_recording(path, sensor_size="auto") as reader:
            assert reader.sensor_size == (260, 346) and reader.num_events == 3


def test_auto_sizes_follow_the_documented_list():
    with pytest.warns(UserWarning) as caught:
        assert auto_sensor_size(239, 179, "a") == (180, 240)
        assert auto_sensor_size(240, 100, "b") == (260, 346)  # DAVIS346 has fewer pixels than 320 x 320
        assert auto_sensor_size(300, 300, "c") == (320, 320)
        assert auto_sensor_size(639, 479, "d") == (480, 640)
        assert auto_sensor_size(700, 100, "e") == (720, 1280)
        assert auto_sensor_size(1500, 10, "f") == (11, 1501)  # no known sensor: the events' bounds
    assert len(caught) == 6 and "no known sensor holds every event" in str(caught[-1].message)


def test_a_file_with_its_own_geometry_keeps_it_and_says_so(tmp_path, events):
    from envs.events import Events
    from envs.readers import write_h5

    x, y, t, p = events
    path = write_h5(tmp_path / "own.h5", Events.create(x, y, t, p, SENSOR))
    with pytest.warns(UserWarning, match=r"stores its sensor size, 48x64 .*which it keeps"):
        with open_recording(path, sensor_size=(100, 100)) as reader:
            assert reader.sensor_size == SENSOR


@pytest.mark.parametrize("value", [["48"], ["48", "0"], ["48", "x"], ["1", "2", "3"], ["Auto"]])
def test_a_bad_sensor_size_is_refused_by_the_parser(value, capsys):
    with pytest.raises(SystemExit) as exit_:
        convert_command.main(["in.raw", "out.h5", "--sensor-size", *value])
    assert exit_.value.code == 2
    assert "argument --sensor-size: expected H W" in capsys.readouterr().err
