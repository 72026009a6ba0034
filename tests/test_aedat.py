"""AEDAT4 recordings through the real ``aedat`` decoder (the test extra installs it), on files
in the AEDAT 4.0 container format written by ``tests/aedat4_writer.py``."""

from __future__ import annotations

import re

import aedat  # noqa: F401  (the test extra: these tests must run, not skip)
import numpy as np
import pytest

from envs.events import EventError
from envs.readers import FormatError, open_recording
from envs.readers.aedat import AedatReader
from envs.windows import iter_windows
from tests.aedat4_writer import COMPRESSIONS, MAGIC, Stream, event_packet, frame_packet, imu_packet, write_aedat4

SENSOR = (26, 34)  # (height, width)
T0 = 1_700_000_000_000_000  # DV times are the camera's absolute µs


def _events(rng, n, t_from, t_to):
    h, w = SENSOR
    t = np.sort(rng.integers(t_from, t_to, n)).astype(np.int64)
    t[n // 2 : n // 2 + 4] = t[n // 2]  # repeated timestamps
    return t, rng.integers(0, w, n), rng.integers(0, h, n), rng.integers(0, 2, n).astype(bool)


def _packets(t, x, y, on, sizes):
    """(stream 0, event packet) for consecutive slices of the given sizes."""
    bounds = np.cumsum([0, *sizes])
    return [(0, event_packet(t[a:b], x[a:b], y[a:b], on[a:b])) for a, b in zip(bounds[:-1], bounds[1:])]


def _at(path) -> str:
    """A regular expression for the start of an error message naming ``path``."""
    return "^" + re.escape(str(path))


def _assert_events(ev, t, x, y, on):
    np.testing.assert_array_equal(ev.t, t)
    np.testing.assert_array_equal(ev.x, x)
    np.testing.assert_array_equal(ev.y, y)
    np.testing.assert_array_equal(ev.p, np.where(on, 1, -1))


def _davis_file(path, rng, *, compression="none", data_table=True):
    """A DAVIS-like recording: 2000 events in 5 packets (one of them empty) over 100 ms,
    frames (8-bit full size, 16-bit and BGR at an offset) and IMU packets in between."""
    h, w = SENSOR
    t, x, y, on = _events(rng, 2000, T0, T0 + 100_000)
    gray = rng.integers(0, 256, SENSOR, dtype=np.uint8)
    gray16 = rng.integers(0, 65536, (10, 12), dtype=np.uint16)
    bgr = rng.integers(0, 256, (8, 9, 3), dtype=np.uint8)
    events = _packets(t, x, y, on, (700, 0, 500, 600, 200))
    imu = (1, imu_packet(t[:4], rng.random((4, 3), dtype=np.float32), rng.random((4, 3), dtype=np.float32)))
    frames = [(2, frame_packet(int(t[0]), gray)),
              (2, frame_packet(int(t[900]), gray16, format="gray16", offset=(5, 4))),
              (2, frame_packet(int(t[-1]), bgr, format="bgr", offset=(w - 9, h - 8)))]
    packets = [frames[0], events[0], imu, events[1], events[2], frames[1], events[3], imu, events[4], frames[2]]
    streams = {0: Stream("EVTS", w, h), 1: Stream("IMUS"), 2: Stream("FRME", w, h)}
    write_aedat4(path, streams, packets, compression=compression, data_table=data_table)
    expected_frames = [gray, np.zeros(SENSOR, np.uint8), np.zeros(SENSOR, np.uint8)]
    expected_frames[1][4:14, 5:17] = gray16 >> 8
    expected_frames[2][h - 8 :, w - 9 :] = np.rint(bgr.astype(np.float32).mean(axis=2))
    frame_t = [int(t[0]), int(t[900]), int(t[-1])]
    return (t, x, y, on), expected_frames, frame_t


@pytest.mark.parametrize("compression", sorted(COMPRESSIONS))
def test_round_trip_is_exact(tmp_path, rng, compression):
    path = tmp_path / "davis.aedat4"
    (t, x, y, on), frames, frame_t = _davis_file(path, rng, compression=compression)
    assert path.read_bytes().startswith(MAGIC)
    with open_recording(path, cache_dir=tmp_path) as r:
        assert isinstance(r, AedatReader)
        assert r.sensor_size == SENSOR and r.num_events == len(t)
        assert r.t_start == t[0] and r.t_end == t[-1] + 1
        _assert_events(r.events_range(0, len(t)), t, x, y, on)
        np.testing.assert_array_equal(r.frame_timestamps(), frame_t)
        for k, image in enumerate(frames):
            np.testing.assert_array_equal(r.frame(k), image)


def test_without_a_data_table_reads_the_same(tmp_path, rng):
    """dataTablePosition -1 (a recording that was not closed): read to the end of the file."""
    path = tmp_path / "interrupted.aedat4"
    (t, x, y, on), frames, _ = _davis_file(path, rng, data_table=False)
    with open_recording(path, cache_dir=tmp_path) as r:
        _assert_events(r.events_range(0, r.num_events), t, x, y, on)
        np.testing.assert_array_equal(r.frame(1), frames[1])


def test_windows_across_packet_boundaries(tmp_path, rng):
    """Time windows that start in one packet and end in the next hold exactly their events."""
    path = tmp_path / "davis.aedat4"
    (t, x, y, on), _, _ = _davis_file(path, rng)
    boundaries = t[[700, 1200, 1800]]  # first events of packets 2, 3 and 4
    with open_recording(path, cache_dir=tmp_path) as r:
        windows = list(iter_windows(r, "time", 7_000))
        assert sum(len(w.events) for w in windows) == len(t)
        straddling = 0
        for w in windows:
            inside = (t >= w.t_start) & (t < w.t_end)
            _assert_events(w.events, t[inside], x[inside], y[inside], on[inside])
            straddling += bool(((boundaries > w.t_start) & (boundaries < w.t_end)).any())
        assert straddling >= 2


def test_a_chosen_event_stream(tmp_path, rng):
    h, w = SENSOR
    t, x, y, on = _events(rng, 300, T0, T0 + 5_000)
    t2, x2, y2, on2 = _events(rng, 200, T0, T0 + 5_000)
    streams = {3: Stream("EVTS", w, h), 7: Stream("EVTS", w, h), 8: Stream("IMUS")}
    path = write_aedat4(tmp_path / "two.aedat4", streams,
                        [(7, event_packet(t2, x2, y2, on2)), (3, event_packet(t, x, y, on))])
    with open_recording(path, cache_dir=tmp_path) as r:  # default: the lowest id
        _assert_events(r.events_range(0, r.num_events), t, x, y, on)
    with open_recording(path, cache_dir=tmp_path, stream_id=7) as r:
        _assert_events(r.events_range(0, r.num_events), t2, x2, y2, on2)
    message = r": stream 8 is not a polarity event stream; the file holds .*stream 8: imus$"
    with pytest.raises(FormatError, match=_at(path) + message):
        open_recording(path, cache_dir=tmp_path, stream_id=8)


def test_close_removes_the_decoded_copy(tmp_path, rng):
    path = tmp_path / "davis.aedat4"
    _davis_file(path, rng)
    cache = tmp_path / "cache"
    cache.mkdir()
    r = open_recording(path, cache_dir=cache)
    assert len(list(cache.iterdir())) == 1
    r.close()
    assert list(cache.iterdir()) == []


# ----------------------------------------------------------------------------------- bad files
@pytest.fixture
def cache(tmp_path):
    """The decoded copies' folder; every test below checks that a failure leaves it empty."""
    folder = tmp_path / "cache"
    folder.mkdir()
    yield folder
    assert list(folder.iterdir()) == []


@pytest.mark.parametrize("compression", ["none", "zstd"])
def test_a_cut_file_names_the_file(tmp_path, cache, compression):
    path, interrupted = tmp_path / "davis.aedat4", tmp_path / "interrupted.aedat4"
    (t, *_), _, _ = _davis_file(path, np.random.default_rng(7), compression=compression)
    _davis_file(interrupted, np.random.default_rng(7), compression=compression, data_table=False)
    data = path.read_bytes()
    packets_start, table_start = data.index(b"</dv>") + 8, interrupted.stat().st_size
    assert data[:table_start] != interrupted.read_bytes()  # the headers differ: dataTablePosition
    cut = tmp_path / "cut.aedat4"
    for size in (len(MAGIC) + 2, packets_start - 100, packets_start + 30, table_start // 2, table_start - 1):
        cut.write_bytes(data[:size])
        with pytest.raises(FormatError, match=_at(cut) + r": .*cannot be read \(.+\).*the file is cut short"):
            open_recording(cut, cache_dir=cache)
    cut.write_bytes(data[: table_start + 10])  # only the data table is cut: every packet is there
    with open_recording(cut, cache_dir=cache) as r:
        assert r.num_events == len(t)


def test_a_file_cut_at_a_packet_boundary_without_data_table_keeps_its_whole_packets(tmp_path, rng, cache):
    """Nothing marks the end of an interrupted recording: whole packets are all there is."""
    t, x, y, on = _events(rng, 400, T0, T0 + 10_000)
    h, w = SENSOR
    path = write_aedat4(tmp_path / "rec.aedat4", {0: Stream("EVTS", w, h)}, _packets(t, x, y, on, (250, 150)),
                        data_table=False)
    last_packet = event_packet(t[250:], x[250:], y[250:], on[250:]).flatbuffer
    path.write_bytes(path.read_bytes()[: -(8 + len(last_packet))])
    with open_recording(path, cache_dir=cache) as r:
        _assert_events(r.events_range(0, r.num_events), t[:250], x[:250], y[:250], on[:250])


@pytest.mark.parametrize(
    "content, kind",
    [
        (b"", "an empty file"),
        (b"1468000000.000 12 3 1\n" * 20, "not an AEDAT4 file"),  # a text recording renamed
        (bytes(np.random.default_rng(5).integers(128, 256, 600, dtype=np.uint8)), "not an AEDAT4 file"),
        (b"#!AER-DAT2.0\r\n# This is a raw AE data file\r\n" + bytes(64), "an AEDAT file of another version"),
        (b"#!AER-DAT4.", "cut short: 11 bytes"),
    ],
)
def test_not_aedat4_with_the_extension_names_the_file(tmp_path, cache, content, kind):
    path = tmp_path / "renamed.aedat4"
    path.write_bytes(content)
    with pytest.raises(FormatError, match=_at(path) + rf": {kind}: it starts with .*, an AEDAT4 file starts with"):
        open_recording(path, cache_dir=cache)


def test_a_damaged_header_names_the_file(tmp_path, rng, cache):
    path = tmp_path / "davis.aedat4"
    _davis_file(path, rng)
    data = path.read_bytes()
    # same size, but the description's root is no longer the dv node
    path.write_bytes(data.replace(b"<dv ", b"<xx ", 1).replace(b"</dv>", b"</xx>", 1))
    message = r": the AEDAT4 header cannot be read \(.+\); the file is cut short or damaged$"
    with pytest.raises(FormatError, match=_at(path) + message):
        open_recording(path, cache_dir=cache)


def test_no_polarity_stream_names_the_file(tmp_path, rng, cache):
    h, w = SENSOR
    t = np.arange(T0, T0 + 40, 10)
    streams = {0: Stream("FRME", w, h), 1: Stream("IMUS")}
    packets = [(0, frame_packet(T0, np.zeros(SENSOR, np.uint8))),
               (1, imu_packet(t, np.zeros((4, 3), np.float32), np.zeros((4, 3), np.float32)))]
    path = write_aedat4(tmp_path / "frames_only.aedat4", streams, packets)
    message = rf": no polarity event stream \(EVTS\); the file holds stream 0: frame {w}x{h}, stream 1: imus$"
    with pytest.raises(FormatError, match=_at(path) + message):
        open_recording(path, cache_dir=cache)


def test_unsorted_packets_name_the_file_not_the_copy(tmp_path, rng, cache):
    h, w = SENSOR
    t, x, y, on = _events(rng, 600, T0, T0 + 30_000)
    order = [(0, 200), (400, 600), (200, 400)]  # the third packet goes back in time
    packets = [(0, event_packet(t[a:b], x[a:b], y[a:b], on[a:b])) for a, b in order]
    path = write_aedat4(tmp_path / "unsorted.aedat4", {0: Stream("EVTS", w, h)}, packets, compression="lz4")
    message = rf" \(stream 0, packet 2\): events go back in time: t={t[200]} us follows t={t[599]} us"
    with pytest.raises(EventError, match=_at(path) + message) as err:
        open_recording(path, cache_dir=cache)
    assert str(cache) not in str(err.value)


def test_unsorted_events_inside_a_packet_name_the_file(tmp_path, rng, cache):
    h, w = SENSOR
    t, x, y, on = _events(rng, 300, T0, T0 + 30_000)
    t[150], t[151] = t[151] + 5, t[151]
    path = write_aedat4(tmp_path / "unsorted.aedat4", {0: Stream("EVTS", w, h)}, _packets(t, x, y, on, (100, 200)))
    message = r" \(stream 0, packet 1\): field 't' must be non-decreasing; index 51 "
    with pytest.raises(EventError, match=_at(path) + message) as err:
        open_recording(path, cache_dir=cache)
    assert str(cache) not in str(err.value)


def test_unsorted_frames_name_the_file(tmp_path, rng, cache):
    h, w = SENSOR
    t, x, y, on = _events(rng, 100, T0, T0 + 30_000)
    image = np.zeros(SENSOR, np.uint8)
    packets = [(1, frame_packet(T0 + 500, image)), (0, event_packet(t, x, y, on)), (1, frame_packet(T0 + 100, image))]
    path = write_aedat4(tmp_path / "frames.aedat4", {0: Stream("EVTS", w, h), 1: Stream("FRME", w, h)}, packets)
    message = rf" \(stream 1, packet 2\): frame at t={T0 + 100} us follows a frame at t={T0 + 500} us"
    with pytest.raises(EventError, match=_at(path) + message):
        open_recording(path, cache_dir=cache)


def test_an_interrupted_decode_leaves_no_copy(tmp_path, rng, cache, monkeypatch):
    """Ctrl-C while the file is decoded: the temporary copy and the writer's file go too."""
    path = tmp_path / "davis.aedat4"
    _davis_file(path, rng)
    import envs.readers

    def interrupt(self, events):
        raise KeyboardInterrupt

    monkeypatch.setattr(envs.readers.H5Writer, "append_events", interrupt)
    with pytest.raises(KeyboardInterrupt):
        AedatReader(path, cache_dir=cache)


def test_the_env_reads_aedat4_windows(tmp_path, rng):
    import gymnasium

    import envs  # noqa: F401  (registers EventFlow-v0)

    path = tmp_path / "davis.aedat4"
    (t, *_), _, _ = _davis_file(path, rng)
    cache = tmp_path / "cache"
    cache.mkdir()
    env = gymnasium.make("EventFlow-v0", data=str(path), window="time", window_size=10_000,
                         data_options={"cache_dir": str(cache)})
    _, info = env.reset(seed=0)
    window_t = np.asarray(info["window"].events.t)
    assert len(window_t) > 0
    first = np.searchsorted(t, window_t[0])
    np.testing.assert_array_equal(window_t, t[first : first + len(window_t)])
    _, reward, *_ = env.step(np.zeros(env.action_space.shape, np.float32))
    assert np.isfinite(reward)
    env.close()
    assert list(cache.iterdir()) == []
