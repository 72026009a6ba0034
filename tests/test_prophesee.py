"""Prophesee RAW (EVT 2.0 / EVT 3.0) and DAT readers against small writers that follow the
published word layouts, written here one word at a time (the slow, obvious reference)."""

from __future__ import annotations

import numpy as np
import pytest

from envs.readers import FormatError, H5Reader, open_recording
from envs.readers.prophesee import PropheseeDatReader, PropheseeRawReader, read_raw_header

SENSOR = (720, 1280)  # IMX636


# --- reference writers -----------------------------------------------------------------------
def raw_header(fmt: str, sensor=SENSOR, *, end: bool = True) -> bytes:
    h, w = sensor
    version = {"EVT2": "2.0", "EVT3": "3.0"}.get(fmt, "9.9")
    lines = [
        "% camera_integrator_name Prophesee",
        "% date 2026-01-02 03:04:05",
        f"% evt {version}",
        f"% format {fmt};height={h};width={w}",
        f"% geometry {w}x{h}",
        "% plugin_name hal_plugin_imx636_evk4",
        "% serial_number 00ca0001",
    ] + (["% end"] if end else [])
    return ("\n".join(lines) + "\n").encode("ascii")


def evt2_words(x, y, t, p, *, triggers_every: int = 0) -> np.ndarray:
    """EVT 2.0: a TIME_HIGH word whenever t >> 6 changes, then CD_OFF/CD_ON words; every
    ``triggers_every`` events an EXT_TRIGGER and an OTHERS word (the reader skips both)."""
    words, high = [], None
    for i, (xi, yi, ti, pi) in enumerate(zip(x.tolist(), y.tolist(), t.tolist(), p.tolist())):
        if ti >> 6 != high:
            high = ti >> 6
            words.append((0x8 << 28) | (high & 0x0FFFFFFF))
        words.append(((1 if pi > 0 else 0) << 28) | ((ti & 63) << 22) | (xi << 11) | yi)
        if triggers_every and i % triggers_every == 0:
            words.append((0xA << 28) | ((ti & 63) << 22) | (3 << 8) | (i & 1))
            words.append((0xE << 28) | 0x123)
    return np.array(words, np.uint32)


def evt3_words(x, y, t, p, *, triggers_every: int = 0) -> tuple[np.ndarray, dict]:
    """EVT 3.0. Events must come sorted by (t, y, p, x) without duplicates: that is the order in
    which the words below deliver them. Per group of one (t, y, p): TIME_HIGH / TIME_LOW /
    ADDR_Y when they change; then an x whose next event lies within 12 pixels opens a vector
    (VECT_BASE_X, then VECT_12 and VECT_8 in turn, each advancing the base, while the next event
    lies within reach), any other x is a single ADDR_X. Returns the words and a count of each type."""
    words, counts = [], {k: 0 for k in ("th", "tl", "y", "x", "base", "v12", "v8", "trigger")}

    def put(kind, value):
        words.append((kind << 12) | value)

    high = low = row = None
    n, i = len(t), 0
    x, y, t, p = (a.tolist() for a in (x, y, t, p))
    while i < n:
        j = i
        while j < n and (t[j], y[j], p[j]) == (t[i], y[i], p[i]):
            j += 1
        pol = 1 if p[i] > 0 else 0
        if t[i] >> 12 != high:
            high = t[i] >> 12
            put(0x8, high & 0xFFF)
            counts["th"] += 1
            low = None
        if t[i] & 0xFFF != low:
            low = t[i] & 0xFFF
            put(0x6, low)
            counts["tl"] += 1
        if y[i] != row:
            row = y[i]
            put(0x0, row)
            counts["y"] += 1
        xs, k, use_12 = x[i:j], 0, True
        while k < len(xs):
            if k + 1 < len(xs) and xs[k + 1] - xs[k] < 12:
                base = xs[k]
                put(0x3, (pol << 11) | base)
                counts["base"] += 1
                while k < len(xs) and xs[k] < base + (12 if use_12 else 8):
                    width = 12 if use_12 else 8
                    mask = 0
                    while k < len(xs) and xs[k] < base + width:
                        mask |= 1 << (xs[k] - base)
                        k += 1
                    put(0x4 if width == 12 else 0x5, mask)
                    counts["v12" if width == 12 else "v8"] += 1
                    base += width
                    use_12 = not use_12
            else:
                put(0x2, (pol << 11) | xs[k])
                counts["x"] += 1
                k += 1
        if triggers_every and (i // triggers_every) != (j // triggers_every):
            put(0xA, (2 << 8) | 1)  # EXT_TRIGGER
            put(0xE, 0x001)  # OTHERS ...
            put(0xF, 0xABC)  # ... and a CONTINUED_12
            counts["trigger"] += 1
        i = j
    return np.array(words, np.uint16), counts


def dat_bytes(x, y, t, p, sensor=(480, 640), event_type: int = 0x0C) -> bytes:
    h, w = sensor
    header = f"% Data file containing CD events\n% Date 2026-01-02 03:04:05\n% Version 2\n% Width {w}\n% Height {h}\n"
    records = np.stack([t.astype(np.int64) & 0xFFFFFFFF,
                        x.astype(np.int64) | (y.astype(np.int64) << 14) | ((p > 0).astype(np.int64) << 28)], 1)
    return header.encode() + bytes([event_type, 8]) + records.astype("<u4").tobytes()


def sorted_events(rng, n, sensor, t0, span, *, clustered: bool = False):
    """n distinct events sorted by (t, y, p, x); clustered: many share t, y and p (vector material)."""
    h, w = sensor
    if clustered:
        m = max(1, -(-n // 6))
        t = np.repeat(np.sort(rng.integers(t0, t0 + span, m)), 6)[:n]
        y = np.repeat(rng.integers(0, h, m), 6)[:n]
        p = np.repeat(rng.integers(0, 2, m), 6)[:n]
        x = np.clip(np.repeat(rng.integers(0, w - 40, m), 6)[:n] + rng.integers(0, 40, n), 0, w - 1)
    else:
        t, y, p, x = np.sort(rng.integers(t0, t0 + span, n)), rng.integers(0, h, n), rng.integers(0, 2, n), rng.integers(0, w, n)
    order = np.lexsort((x, p, y, t))
    x, y, t, p = x[order], y[order], t[order], p[order]
    keep = np.ones(len(t), bool)
    keep[1:] = (np.diff(t) != 0) | (np.diff(y) != 0) | (np.diff(p) != 0) | (np.diff(x) != 0)
    return x[keep], y[keep], t[keep].astype(np.int64), p[keep]


def assert_events(ev, x, y, t, p):
    np.testing.assert_array_equal(ev.t, t)
    np.testing.assert_array_equal(ev.x, x)
    np.testing.assert_array_equal(ev.y, y)
    np.testing.assert_array_equal(ev.p, np.where(p > 0, 1, -1))


def write(path, header: bytes, words: np.ndarray):
    path.write_bytes(header + words.astype(words.dtype.newbyteorder("<")).tobytes())
    return path


# --- round trips -----------------------------------------------------------------------------
@pytest.mark.parametrize("fmt", ["EVT2", "EVT3"])
def test_raw_round_trip_across_chunks_and_the_time_wrap(tmp_path, rng, fmt):
    bits = 34 if fmt == "EVT2" else 24  # the time base wraps at 2^bits µs
    before = sorted_events(rng, 3000, SENSOR, (1 << bits) - 40_000, 35_000)
    across = sorted_events(rng, 3000, SENSOR, (1 << bits) - 5_000, 45_000, clustered=True)
    x, y, t, p = (np.concatenate(pair) for pair in zip(before, across))
    assert t[0] < (1 << bits) < t[-1]
    if fmt == "EVT2":
        words, counts = evt2_words(x, y, t, p, triggers_every=37), None
    else:
        words, counts = evt3_words(x, y, t, p, triggers_every=37)
        assert min(counts.values()) > 10, counts  # every word type is exercised
    path = write(tmp_path / f"rec_{fmt}.raw", raw_header(fmt), words)
    with PropheseeRawReader(path, chunk_words=997, index_dir=tmp_path / "index") as r:
        assert r.format == fmt and r.sensor_size == SENSOR and r.num_events == len(t)
        assert r.header.camera["serial_number"] == "00ca0001"
        assert r.header.camera["plugin_name"] == "hal_plugin_imx636_evk4"
        assert r.reordered_events == 0
        assert_events(r.events_range(0, r.num_events), x, y, t, p)
        assert (r.t_start, r.t_end) == (t[0], t[-1] + 1)
        for q in (t[0] - 5, t[0], t[1234] + 1, 1 << bits, t[-1], t[-1] + 1, t[len(t) // 2]):
            assert r.index_at(int(q)) == np.searchsorted(t, q)
        mid = r.events_between(int(t[2000]), int(t[4000]))
        i0, i1 = np.searchsorted(t, [t[2000], t[4000]])
        assert_events(mid, x[i0:i1], y[i0:i1], t[i0:i1], p[i0:i1])
        assert r.time_of(4321) == t[4321]


def test_evt3_vector_base_advances_over_empty_masks(tmp_path):
    """VECT_12 / VECT_8 advance the base by 12 / 8 even when the mask holds no event."""
    w = [0x8000 | 1, 0x6000 | 7, 0x0000 | 5, 0x3000 | (1 << 11) | 100, 0x4000 | 0b1, 0x4000, 0x5000 | 0b1000_0001,
         0x2000 | 3, 0xA000 | 0x101, 0x3000 | 10, 0x5000 | 0b10]
    path = write(tmp_path / "v.raw", raw_header("EVT3"), np.array(w, np.uint16))
    with PropheseeRawReader(path, index_dir=tmp_path) as r:
        ev = r.events_range(0, r.num_events)
    t = (1 << 12) | 7
    np.testing.assert_array_equal(ev.x, [100, 124, 131, 3, 11])
    np.testing.assert_array_equal(ev.y, [5] * 5)
    np.testing.assert_array_equal(ev.p, [1, 1, 1, -1, -1])
    np.testing.assert_array_equal(ev.t, [t] * 5)


def test_evt3_time_low_passing_4096_without_a_time_high(tmp_path):
    """Writers that send no TIME_HIGH when the time base passes a multiple of 4096 µs: a TIME_LOW
    below the previous one with no TIME_HIGH between them steps the time high, also when a chunk
    boundary falls between them; a TIME_HIGH between them (a camera's stream) does not."""
    words = [0x8000 | 2, 0x6000 | 4000, 0x0000 | 1, 0x2000 | 10,  # t = 2 * 4096 + 4000
             0x6000 | 50, 0x2000 | 11,  # no TIME_HIGH: t = 3 * 4096 + 50
             0x6000 | 60, 0x2000 | 12,  # t = 3 * 4096 + 60
             0x8000 | 4, 0x6000 | 30, 0x2000 | 13,  # a TIME_HIGH: t = 4 * 4096 + 30
             0x6000 | 20, 0x2000 | 14]  # looped again: t = 5 * 4096 + 20
    expected = [2 * 4096 + 4000, 3 * 4096 + 50, 3 * 4096 + 60, 4 * 4096 + 30, 5 * 4096 + 20]
    path = write(tmp_path / "loop.raw", raw_header("EVT3"), np.array(words, np.uint16))
    for chunk_words in (1, 2, 3, 5, 9, 100):
        with PropheseeRawReader(path, chunk_words=chunk_words, index_dir=tmp_path) as r:
            np.testing.assert_array_equal(r.events_range(0, r.num_events).t, expected)
            np.testing.assert_array_equal(r.events_range(0, r.num_events).x, [10, 11, 12, 13, 14])


def test_events_before_the_first_time_high_are_dropped(tmp_path):
    first = (0 << 28) | (5 << 22) | (1 << 11) | 2  # a CD_OFF word with no time base yet
    words = np.array([first, 0x8 << 28 | 10, (1 << 28) | (3 << 22) | (4 << 11) | 6], np.uint32)
    with PropheseeRawReader(write(tmp_path / "a.raw", raw_header("EVT2"), words), index_dir=tmp_path) as r:
        ev = r.events_range(0, r.num_events)
    np.testing.assert_array_equal(ev.t, [(10 << 6) | 3])
    np.testing.assert_array_equal(ev.x, [4])


def test_a_late_stamped_event_takes_the_previous_time(tmp_path, rng):
    x, y, t, p = sorted_events(rng, 50, SENSOR, 1000, 10_000)
    t_bad = t.copy()
    t_bad[20] = t[19] - 3  # a few µs early
    words = evt2_words(x, y, t_bad, p)
    with pytest.warns(UserWarning, match="1 events were stamped earlier"):
        r = PropheseeRawReader(write(tmp_path / "late.raw", raw_header("EVT2"), words), index_dir=tmp_path)
    with r:
        assert r.reordered_events == 1
        fixed = t_bad.copy()
        fixed[20] = t[19]
        np.testing.assert_array_equal(r.events_range(0, r.num_events).t, fixed)


def test_dat_round_trip_across_the_32_bit_wrap(tmp_path, rng):
    x, y, t, p = sorted_events(rng, 5000, (480, 640), (1 << 32) - 20_000, 60_000)
    path = tmp_path / "rec_cd.dat"
    path.write_bytes(dat_bytes(x, y, t, p))
    with PropheseeDatReader(path, chunk_words=613, index_dir=tmp_path / "index") as r:
        assert r.sensor_size == (480, 640) and r.num_events == len(t)
        assert r.header["Version"] == "2"
        assert_events(r.events_range(0, r.num_events), x, y, t, p)
        for q in (t[0], 1 << 32, t[-1] + 1, t[2500]):
            assert r.index_at(int(q)) == np.searchsorted(t, q)


def test_dat_event2d_type_reads_too(tmp_path, rng):
    x, y, t, p = sorted_events(rng, 100, (240, 304), 0, 10_000)
    path = tmp_path / "gen1_td.dat"
    path.write_bytes(dat_bytes(x, y, t, p, sensor=(240, 304), event_type=0x00))
    with open_recording(path) as r:
        assert isinstance(r, PropheseeDatReader)
        assert_events(r.events_range(0, r.num_events), x, y, t, p)


# --- streaming and the cached index --------------------------------------------------------------
def test_index_is_cached_and_a_middle_window_decodes_only_its_chunks(tmp_path, rng, monkeypatch):
    x, y, t, p = sorted_events(rng, 20_000, SENSOR, 0, 2_000_000)
    path = write(tmp_path / "long.raw", raw_header("EVT3"), evt3_words(x, y, t, p)[0])
    monkeypatch.setenv("EVFLOW_CACHE", str(tmp_path / "cache"))
    with PropheseeRawReader(path, chunk_words=1000) as r:
        assert r.index_path is not None and r.index_path.parent == tmp_path / "cache" / "prophesee-index"
        assert r.reordered_events == 0
        n_chunks = len(r._t_last)
    assert n_chunks > 40

    def no_rebuild(self):
        raise AssertionError("the index was rebuilt")

    monkeypatch.setattr(PropheseeRawReader, "_build_index", no_rebuild)
    with PropheseeRawReader(path, chunk_words=1000) as r:
        read = []
        inner = r._read_words
        r._read_words = lambda k: read.append(k) or inner(k)
        r._decoded.clear()
        ev = r.events_between(1_000_000, 1_010_000)
        i0, i1 = np.searchsorted(t, [1_000_000, 1_010_000])
        assert_events(ev, x[i0:i1], y[i0:i1], t[i0:i1], p[i0:i1])
        assert 1 <= len(set(read)) <= 3 and min(read) > n_chunks // 3  # only chunks near the middle
    # a changed file gets a new index
    path.write_bytes(path.read_bytes()[: -2 * 10])
    monkeypatch.undo()
    with PropheseeRawReader(path, chunk_words=1000, index_dir=tmp_path / "cache" / "prophesee-index") as r:
        assert r.num_events < len(t)


def test_open_recording_env_and_convert_read_prophesee_files(tmp_path, rng):
    from envs.env import EventFlowEnv
    from envs.readers.convert import convert_recording

    sensor = (48, 64)
    x, y, t, p = sorted_events(rng, 4000, sensor, 10_000, 200_000)
    raw = write(tmp_path / "cam.raw", raw_header("EVT3", sensor), evt3_words(x, y, t, p)[0])
    headered = write(tmp_path / "cam_noext", raw_header("EVT2", sensor), evt2_words(x, y, t, p))
    dat = tmp_path / "cam.dat"
    dat.write_bytes(dat_bytes(x, y, t, p, sensor=sensor))
    for path, cls in ((raw, PropheseeRawReader), (headered, PropheseeRawReader), (dat, PropheseeDatReader)):
        with open_recording(path, index_dir=tmp_path / "index") as r:
            assert isinstance(r, cls)
            assert_events(r.events_range(0, r.num_events), x, y, t, p)
            out = convert_recording(r, tmp_path / f"{path.name}.h5")
        with H5Reader(out) as h:
            assert_events(h.events_range(0, h.num_events), x, y, t, p)
    env = EventFlowEnv(str(raw), window="time", window_size=20_000, compute_reward=False, data_options={"index_dir": tmp_path / "index"})
    obs, info = env.reset(options={"sequence": 0})
    seen = len(info["window"].events.t)
    truncated = False
    while not truncated:
        obs, _, _, truncated, info = env.step(np.zeros((2,) + sensor, np.float32))
        seen += len(info["window"].events.t) if not truncated else 0
    assert seen == len(t) and obs["count_image"].shape == (2,) + sensor


# --- bad input -----------------------------------------------------------------------------------
def test_truncated_raw_names_the_file(tmp_path, rng):
    x, y, t, p = sorted_events(rng, 100, SENSOR, 0, 10_000)
    path = tmp_path / "cut.raw"
    path.write_bytes((raw_header("EVT2") + evt2_words(x, y, t, p).tobytes())[:-3])
    with pytest.raises(FormatError, match=r"cut\.raw: truncated.*1 bytes into a word"):
        PropheseeRawReader(path, index_dir=tmp_path)
    head_only = tmp_path / "head.raw"
    head_only.write_bytes(raw_header("EVT3")[:-5])  # cut inside the header's last line
    with pytest.raises(FormatError, match=r"head\.raw: the header line .* has no end"):
        open_recording(head_only)


def test_unknown_evt_version_names_the_file(tmp_path):
    path = write(tmp_path / "v21.raw", raw_header("EVT21"), np.zeros(4, np.uint32))
    with pytest.raises(FormatError, match=r"v21\.raw: unsupported event format 'EVT21'.*EVT 2\.0 and EVT 3\.0"):
        open_recording(path)
    old = tmp_path / "old.raw"
    old.write_bytes(b"% evt 4.0\n% geometry 640x480\n" + bytes(8))
    with pytest.raises(FormatError, match=r"old\.raw: unsupported event format 'EVT 4\.0'"):
        read_raw_header(old)


def test_raw_without_header_names_the_file(tmp_path, rng):
    x, y, t, p = sorted_events(rng, 10, SENSOR, 0, 1000)
    path = tmp_path / "bare.raw"
    path.write_bytes(evt2_words(x, y, t, p).tobytes())
    with pytest.raises(FormatError, match=r"bare\.raw: no RAW header"):
        open_recording(path)
    no_geometry = tmp_path / "nogeo.raw"
    no_geometry.write_bytes(b"% evt 3.0\n% end\n" + bytes(4))
    with pytest.raises(FormatError, match=r"nogeo\.raw: the RAW header gives no geometry"):
        open_recording(no_geometry)
    with open_recording(no_geometry, sensor_size=(10, 10), index_dir=tmp_path) as r:
        assert r.num_events == 0


def test_dat_with_a_wrong_event_type_names_the_file(tmp_path, rng):
    x, y, t, p = sorted_events(rng, 10, (480, 640), 0, 1000)
    path = tmp_path / "trig.dat"
    path.write_bytes(dat_bytes(x, y, t, p, event_type=0x0E))
    with pytest.raises(FormatError, match=r"trig\.dat: DAT event type 0x0E is external-trigger events"):
        open_recording(path)
    odd = tmp_path / "odd.dat"
    odd.write_bytes(dat_bytes(x, y, t, p, event_type=0x42))
    with pytest.raises(FormatError, match=r"odd\.dat: DAT event type 0x42 is an unknown event type"):
        open_recording(odd)


def test_geometry_too_small_for_the_events_names_the_file(tmp_path, rng):
    x, y, t, p = sorted_events(rng, 100, SENSOR, 0, 10_000)
    path = write(tmp_path / "small.raw", raw_header("EVT2", (100, 100)), evt2_words(x, y, t, p))
    with pytest.raises(FormatError, match=r"small\.raw: event [xy]=\d+ outside the 100x100 sensor"):
        open_recording(path, index_dir=tmp_path)
    assert not list(tmp_path.glob("*.npz"))  # nothing half-written


@pytest.mark.parametrize("fmt", ["EVT2", "EVT3"])
def test_benchmark_encoders_agree_with_the_reader(tmp_path, fmt):
    """The vectorised encoders of evflow_cli/commands/bench_prophesee.py write what the reader reads back."""
    from evflow_cli.commands import bench_prophesee as bench

    path = bench.write_raw(tmp_path / "b.raw", fmt, 30_000, 2e6, chunk=7_000)
    rng = np.random.default_rng(0)  # the same draws as write_raw(seed=0)
    parts = []
    for k, i0 in enumerate(range(0, 30_000, 7_000)):
        n = min(7_000, 30_000 - i0)
        span = 7_000 / 2e6 * 1e6
        t = np.sort(rng.integers(int(k * span), int(k * span + span * n / 7_000), n))
        parts.append((rng.integers(0, 1280, n), rng.integers(0, 720, n), rng.integers(0, 2, n), t))
    x, y, p, t = (np.concatenate(c) for c in zip(*parts))
    with PropheseeRawReader(path, index_dir=tmp_path) as r:
        assert_events(r.events_range(0, r.num_events), x, y, t, p)


@pytest.mark.parametrize("encoding", ["evt2", "evt3", "dat"])
def test_files_written_by_expelliarmus(tmp_path, rng, encoding):
    """An independent encoder, where installed: expelliarmus writes RAW (no geometry in its
    header, no TIME_HIGH words in EVT 3.0) and DAT files; we read back what it was given.
    Its EVT 3.0 files hold only when events are less than 4096 µs apart (its own reader loses
    the time otherwise), so the gaps here stay below 2000 µs."""
    expelliarmus = pytest.importorskip("expelliarmus")
    n = 40_000
    events = np.zeros(n, np.dtype([("t", "<i8"), ("x", "<i2"), ("y", "<i2"), ("p", "u1")]))
    events["t"] = np.cumsum(rng.integers(0, 2000, n))  # ~20 s: past the 24-bit EVT 3.0 time base
    events["x"], events["y"], events["p"] = rng.integers(0, 1280, n), rng.integers(0, 720, n), rng.integers(0, 2, n)
    events["t"][1::2], events["y"][1::2], events["p"][1::2] = events["t"][::2], events["y"][::2], events["p"][::2]
    events["x"][1::2] = np.minimum(events["x"][::2] + rng.integers(1, 11, n // 2), 1279)
    path = tmp_path / f"x.{'dat' if encoding == 'dat' else 'raw'}"
    expelliarmus.Wizard(encoding=encoding).save(path, events)
    with open_recording(path, sensor_size=SENSOR, index_dir=tmp_path, chunk_words=997) as r:
        assert r.reordered_events == 0
        assert_events(r.events_range(0, r.num_events), events["x"], events["y"], events["t"], events["p"])
