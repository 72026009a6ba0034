"""Prophesee recordings: RAW files in EVT 2.0 or EVT 3.0, and DAT files of CD events.

Both are decoded here with numpy, vectorised over whole chunks of words (no Python loop per
event), following Prophesee's published format descriptions:

- **RAW header**: ASCII lines ``% key value`` (``% evt 3.0``, ``% format EVT3;height=720;width=1280``,
  ``% geometry 1280x720``, ``% camera_integrator_name ...``, ``% serial_number ...``), ended by
  ``% end`` or by the first line that does not start with ``%``; then little-endian words.
- **EVT 2.0** (32-bit words, type in bits 31..28): CD_OFF 0x0 / CD_ON 0x1 (bits 27..22: the 6
  low bits of the time, 21..11: x, 10..0: y); EVT_TIME_HIGH 0x8 (bits 27..0: time >> 6);
  EXT_TRIGGER 0xA, OTHERS 0xE, CONTINUED 0xF (skipped). Time is 34 bits and wraps every ~4.8 h.
- **EVT 3.0** (16-bit words, type in bits 15..12): EVT_ADDR_Y 0x0 (bits 10..0: y), EVT_ADDR_X 0x2
  (one event; bit 11: polarity, 10..0: x), VECT_BASE_X 0x3 (base x and polarity of the vectors
  that follow), VECT_12 0x4 / VECT_8 0x5 (a validity mask over 12 / 8 pixels from the base x,
  which then advances by 12 / 8), EVT_TIME_LOW 0x6 / EVT_TIME_HIGH 0x8 (the low / high 12 bits
  of the 24-bit time base, which wraps every ~16.8 s); EXT_TRIGGER 0xA, OTHERS 0xE and the
  CONTINUED words are skipped.
- **DAT**: ``%`` header lines (``% Width 640``, ``% Height 480``, ``% Version 2``), one byte of
  event type (0x00 Event2d or 0x0C EventCd are read; 0x0E external triggers are refused) and one
  of event size (8), then records of a uint32 time (µs) and a uint32 with x in bits 0..13, y in
  bits 14..27 and the polarity in bits 28..31.

**Geometry.** From the header; older cameras and converters write none: then ``sensor_size=(height,
width)`` (``--sensor-size H W`` on the commands, ``data_options={"sensor_size": ...}`` in the env),
or ``"auto"``: the smallest known sensor holding every event, with a warning naming it.

Time-base wrap-arounds are unfolded (times are absolute µs since the camera's clock start, as
Metavision reports them). Events whose time, row or x is not yet known (before the first
time-high word; in EVT 3.0 also before the first TIME_LOW, EVT_ADDR_Y or, for vectors,
VECT_BASE_X) are dropped. The rare event stamped earlier than one before it is given that earlier
time (the project's events never go back in time); ``reordered_events`` counts them. DAT's 32-bit
counter wraps only when it really does (a small step forward across 2^32, read as serial-number
arithmetic); a record stamped more than ``DAT_REORDER_TOLERANCE_US`` back is refused, naming the
file and its byte offset, instead of being taken for a wrap. Times spanning more than
``envs.events.MAX_SPAN_US`` (24 h) are refused as corrupt; header values that are not whole
numbers of pixels (``height=abc``, ``% Width abc``) are refused naming the file and the line.

**Streaming.** The file is cut into chunks of a fixed number of words. On first open the
whole file is decoded once, chunk by chunk, and for every chunk the decoder state at its start
(time base, y, base x...), its first event index and its last event time are kept: the *time
index*. It is cached on disk (``index_dir``, default ``$EVFLOW_CACHE/prophesee-index``; in
memory only when the cache is off), keyed by the file's path, size and modification time, so
later opens read it instead of decoding. The index also keeps each chunk's largest x and y, so
every open, from the cache or not, checks the events against the sensor size it was given. A window is then read by decoding only the one or two
chunks that hold it (the last chunks decoded are kept), wherever it lies in the file: memory
stays a few chunks deep however long the recording.
"""

from __future__ import annotations

import hashlib
import os
import tempfile
import warnings
from collections import OrderedDict
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np

from envs.cache import cache_root
from envs.events import MAX_SENSOR_SIDE, MAX_SPAN_US, Events
from envs.readers._common import SENSOR_SIZE_HINT, auto_sensor_size
from envs.readers.base import EventReader, FormatError

__all__ = ["RawHeader", "read_raw_header", "PropheseeRawReader", "PropheseeDatReader", "RAW_FORMATS",
           "DAT_EVENT_TYPES"]

RAW_FORMATS = ("EVT2", "EVT3")
# DAT event-type byte: the CD layouts read here (Event2d, EventCd); 0x0E is EventExtTrigger
DAT_EVENT_TYPES = {0x00: "Event2d", 0x0C: "EventCd"}
_DAT_TRIGGER = 0x0E
_INDEX_VERSION = 3  # 3: per-chunk coordinate maxima (the geometry is checked on a cached index too)
#: DAT: a record may be stamped this much earlier than one before it (given that earlier time);
#: further back is no wrap of the 32-bit counter and no jitter, but a corrupt record
DAT_REORDER_TOLERANCE_US = 1000
_HEADER_LIMIT = 1 << 16  # bytes of header read at most


@dataclass(frozen=True)
class RawHeader:
    """What a RAW file's ASCII header says.

    format: "EVT2" or "EVT3"; sensor_size: (height, width) or None when the header gives none;
    camera: the other header keys (integrator, plugin, serial number, date...);
    data_offset: bytes from the file start to the first event word.
    """

    format: Literal["EVT2", "EVT3"]
    sensor_size: tuple[int, int] | None
    camera: dict[str, str] = field(default_factory=dict)
    data_offset: int = 0


def _header_lines(path: Path, head: bytes) -> tuple[list[str], int]:
    """The ``%`` lines at the start of ``head`` (without '% ') and the byte offset after them."""
    lines, pos = [], 0
    while pos < len(head) and head[pos : pos + 1] == b"%":
        end = head.find(b"\n", pos)
        if end < 0:
            raise FormatError(f"{path}: the header line at byte {pos} has no end (file truncated inside the header?)")
        raw = head[pos:end]
        try:
            text = raw.decode("ascii").rstrip("\r")
        except UnicodeDecodeError:
            break  # binary data that happens to start with '%': the header ended before it
        pos = end + 1
        text = text[1:].strip()
        if text == "end":
            return lines, pos
        lines.append(text)
    return lines, pos


def _header_size(path: Path, line: str, height: str, width: str) -> tuple[int, int]:
    """(height, width) from header text; anything but two whole numbers in [1, MAX_SENSOR_SIDE]
    raises FormatError naming the file and the header line."""
    try:
        size = (int(height.strip()), int(width.strip()))
    except ValueError:
        size = None
    if size is None or not all(0 < side <= MAX_SENSOR_SIDE for side in size):
        raise FormatError(f"{path}: the header's {line} gives height {height.strip()!r} and width {width.strip()!r}; "
                          f"expected whole numbers of pixels in [1, {MAX_SENSOR_SIDE}] (or {SENSOR_SIZE_HINT})")
    return size


def read_raw_header(path: str | os.PathLike) -> RawHeader:
    """Parse a RAW file's header; a missing header or an EVT version other than 2.0 / 3.0 raises
    FormatError naming the file."""
    path = Path(path)
    with open(path, "rb") as fh:
        head = fh.read(_HEADER_LIMIT)
    if not head.startswith(b"%"):
        raise FormatError(
            f"{path}: no RAW header: a Prophesee RAW file starts with ASCII lines '% key value' "
            "(e.g. '% evt 3.0', '% format EVT3;height=720;width=1280'); this one starts with "
            f"bytes {head[:8].hex(' ')}"
        )
    lines, offset = _header_lines(path, head)
    keys: dict[str, str] = {}
    for line in lines:
        key, _, value = line.partition(" ")
        keys[key.strip()] = value.strip()
    fmt, size = None, None
    if "format" in keys:  # "EVT3;height=720;width=1280"
        name, *options = keys["format"].split(";")
        fmt = name.strip().upper()
        opts = dict(o.split("=", 1) for o in options if "=" in o)
        if "height" in opts and "width" in opts:
            size = _header_size(path, f"'% format {keys['format']}'", opts["height"], opts["width"])
    if fmt is None and "evt" in keys:  # older headers: "% evt 2.0"
        fmt = {"2.0": "EVT2", "3.0": "EVT3"}.get(keys["evt"], f"EVT {keys['evt']}")
    if fmt is None:
        raise FormatError(f"{path}: the RAW header names no event format (no '% format' or '% evt' line)")
    if fmt not in RAW_FORMATS:
        raise FormatError(
            f"{path}: unsupported event format {fmt!r} in the RAW header; supported: EVT 2.0 and EVT 3.0 "
            f"({', '.join(RAW_FORMATS)})"
        )
    if size is None and "geometry" in keys:  # "1280x720" (width x height)
        w, _, h = keys["geometry"].partition("x")
        size = _header_size(path, f"'% geometry {keys['geometry']}' (width x height)", h, w)
    camera = {k: v for k, v in keys.items() if k not in ("format", "evt", "geometry")}
    return RawHeader(fmt, size, camera, offset)


# ---------------------------------------------------------------------------------------------
# Decoders: a chunk of words and the state at its start -> events and the state at its end.
# A state is a small int64 vector; -1 marks "not seen yet".

_EVT2_STATE = ("time_high", "last_t")  # time_high: full (unwrapped) value of the last EVT_TIME_HIGH
# low_after_high: 1 when the last TIME_LOW came after the last TIME_HIGH (see _decode_evt3)
_EVT3_STATE = ("time_high", "time_low", "y", "base_x", "polarity", "last_t", "low_after_high")
_DAT_STATE = ("time", "last_t")  # time: full (unwrapped) time of the last record


def _unwrap(values: np.ndarray, previous: int, bits: int) -> np.ndarray:
    """Unfold a counter of ``bits`` bits that wraps around: a value below the one before it
    starts a new period. previous: the full value before these (-1: none). Returns int64."""
    values = values.astype(np.int64)
    if len(values) == 0:
        return values
    period = np.int64(1) << bits
    if previous >= 0:
        low = np.concatenate([[previous & (period - 1)], values])
        epoch0 = previous >> bits
    else:
        low = np.concatenate([values[:1], values])
        epoch0 = 0
    epochs = epoch0 + np.cumsum(np.diff(low) < 0)
    return values + epochs * period


def _monotonic(t: np.ndarray, last_t: int) -> tuple[np.ndarray, int]:
    """t made non-decreasing after last_t (running maximum); also how many values changed."""
    if len(t) == 0:
        return t, 0
    fixed = np.maximum.accumulate(np.maximum(t, last_t))
    return fixed, int(np.count_nonzero(fixed != t))


def _decode_evt2(words: np.ndarray, state: np.ndarray):
    """words: (N,) uint32. Returns (x, y, t, p, state, reordered)."""
    time_high, last_t = (int(v) for v in state)
    kind = words >> 28
    is_th = kind == 0x8
    th_full = _unwrap(words[is_th] & 0x0FFFFFFF, time_high, 28)
    table = np.concatenate([np.array([time_high], np.int64), th_full])
    th = table[np.cumsum(is_th)]
    cd = np.flatnonzero((kind <= 0x1) & (th >= 0))
    w = words[cd]
    t = (th[cd] << 6) | ((w >> 22) & 0x3F).astype(np.int64)
    t, reordered = _monotonic(t, last_t)
    x = ((w >> 11) & 0x7FF).astype(np.int16)
    y = (w & 0x7FF).astype(np.int16)
    p = kind[cd].astype(np.int8)
    new_state = np.array([table[-1], int(t[-1]) if len(t) else last_t], np.int64)
    return x, y, t, p, new_state, reordered


_POPCOUNT = np.array([bin(m).count("1") for m in range(1 << 12)], np.int64)  # events per vector mask
# _SET_BITS[mask, k]: the position of the k-th set bit of a 12-bit vector mask (pixel offset)
_SET_BITS = np.array([[i for i in range(12) if m >> i & 1] + [0] * (12 - bin(m).count("1")) for m in range(1 << 12)],
                     np.int64)


def _at(where: np.ndarray, is_update: np.ndarray, values: np.ndarray, before: int) -> np.ndarray:
    """At the word positions ``where``: the value of the last update word at or before each
    (``before`` if none in this chunk). values: payloads of the update words, in order."""
    table = np.concatenate([np.array([before], np.int64), values.astype(np.int64)])
    return table[np.cumsum(is_update, dtype=np.int32)[where]]


def _evt3_time_high(is_th, is_tl, payload, carrying, time_high, time_low, low_after_high):
    """The full time high (unfolded, int64) in force at each word of ``carrying``, the time high
    and ``low_after_high`` flag at the chunk's end.

    Besides the TIME_HIGH words, a TIME_LOW below the one before it with no TIME_HIGH between
    them steps the time high by one: the time base passed a multiple of 4096 µs without a
    TIME_HIGH word, as some writers (e.g. expelliarmus) produce. A camera's stream, whose time
    base never goes back, always sends the TIME_HIGH, so this never fires on it.
    """
    th_full = _unwrap(payload[is_th], time_high, 12)
    th_seen = np.cumsum(is_th, dtype=np.int32)  # TIME_HIGH words up to each word
    th = np.concatenate([np.array([time_high], np.int64), th_full])[th_seen[carrying]]
    end_high = int(th_full[-1]) if len(th_full) else time_high
    tl_at = np.flatnonzero(is_tl)
    tl_values = payload[tl_at].astype(np.int64)
    previous_tl = np.concatenate([np.array([time_low], np.int64), tl_values[:-1]])
    previous_seen = np.concatenate([np.array([0], np.int32), th_seen[tl_at][:-1]])
    looped = (tl_values < previous_tl) & (th_seen[tl_at] == previous_seen)
    if len(tl_at) and low_after_high != 1:
        looped[0] = False  # a TIME_HIGH came between the previous chunk's last TIME_LOW and this one
    th_at = np.flatnonzero(is_th)
    if len(th_at) and (not len(tl_at) or th_at[-1] > tl_at[-1]):
        low_after_high = 0
    elif len(tl_at):
        low_after_high = 1
    if looped.any():
        steps = np.zeros(len(is_th), np.int32)
        steps[tl_at[looped]] = 1
        steps_run = np.cumsum(steps, dtype=np.int64)
        at_th = np.concatenate([np.array([0], np.int64), steps_run[is_th]])  # steps before each TIME_HIGH
        th = np.where(th >= 0, th + steps_run[carrying] - at_th[th_seen[carrying]], th)
        if end_high >= 0:
            end_high += int(steps_run[-1] - at_th[-1])
    return th, end_high, low_after_high


def _evt3_vectors(kind, payload, carrying, base_state, pol_state):
    """For the VECT_12 / VECT_8 words among ``carrying``: their first x (the last VECT_BASE_X,
    advanced by 12 / 8 for every vector word since it), polarity and mask (-1 x where no base
    is known yet); and the base and polarity at the chunk's end."""
    is_v12, is_v8, is_base = kind == 0x4, kind == 0x5, kind == 0x3
    step = is_v12 * np.int64(12) + is_v8 * np.int64(8)
    advanced = np.cumsum(step)  # inclusive
    which = np.cumsum(is_base, dtype=np.int32)[carrying]
    base_word = np.concatenate([np.array([base_state], np.int64), payload[is_base].astype(np.int64) & 0x7FF])
    base_mark = np.concatenate([np.array([0], np.int64), advanced[is_base]])
    base_pol = np.concatenate([np.array([pol_state], np.int64), payload[is_base].astype(np.int64) >> 11])
    first_x = base_word[which] + (advanced[carrying] - step[carrying]) - base_mark[which]
    first_x[base_word[which] < 0] = -1
    pay = payload[carrying].astype(np.int64)
    mask = np.where(is_v12[carrying], pay, pay & 0xFF)
    end_base = int(base_word[-1] + advanced[-1] - base_mark[-1]) if base_word[-1] >= 0 else -1
    return first_x, base_pol[which], mask, end_base, int(base_pol[-1])


def _decode_evt3(words: np.ndarray, state: np.ndarray):
    """words: (N,) uint16. Returns (x, y, t, p, state, reordered).

    Only the event-carrying words (ADDR_X, VECT_12, VECT_8) are expanded: each gets the time,
    row and vector base in force at its position (running counts of the update words); a
    vector word then yields one event per set bit of its mask, in pixel order, at its place in
    the stream.
    """
    time_high, time_low, y_state, base_state, pol_state, last_t, low_after_high = (int(v) for v in state)
    kind = (words >> 12).astype(np.uint8)
    payload = words & np.uint16(0x0FFF)
    is_th, is_tl, is_y, is_x = kind == 0x8, kind == 0x6, kind == 0x0, kind == 0x2
    is_vector = (kind == 0x4) | (kind == 0x5)
    carrying = np.flatnonzero(is_x | is_vector)
    th, end_high, low_after_high = _evt3_time_high(is_th, is_tl, payload, carrying, time_high, time_low, low_after_high)
    tl = _at(carrying, is_tl, payload[is_tl], time_low)
    row = _at(carrying, is_y, payload[is_y] & 0x7FF, y_state)
    pay = payload[carrying].astype(np.int64)
    first_x, polarity = pay & 0x7FF, pay >> 11  # ADDR_X words: the event itself
    count = np.ones(len(carrying), np.int64)  # events per carrying word
    has_vectors = bool(is_vector.any())
    end_base, end_pol = base_state, pol_state
    if has_vectors or (kind == 0x3).any():
        vec = is_vector[carrying]
        vx, vpol, mask, end_base, end_pol = _evt3_vectors(kind, payload, carrying, base_state, pol_state)
        first_x[vec], polarity[vec] = vx[vec], vpol[vec]
        count[vec] = np.where(vx[vec] >= 0, _POPCOUNT[mask[vec]], 0)
    count[(th < 0) | (tl < 0) | (row < 0)] = 0  # before the first time base / row: no known time or y
    if not has_vectors:  # one event per ADDR_X word
        source = np.flatnonzero(count > 0)  # which carrying word each event comes from
        x = first_x[source]
    else:
        offset = np.cumsum(count) - count  # each word's first event
        x = np.empty(int(offset[-1] + count[-1]), np.int64)
        source = np.empty(len(x), np.int64)
        single = np.flatnonzero(~vec & (count > 0))
        x[offset[single]], source[offset[single]] = first_x[single], single
        vectors = np.flatnonzero(vec & (count > 0))
        r = np.repeat(vectors, count[vectors])  # the word of each vector event, in word order
        k = np.arange(len(r)) - np.repeat(np.cumsum(count[vectors]) - count[vectors], count[vectors])
        at = offset[r] + k  # the k-th set bit of a mask is its k-th event, in pixel order
        x[at], source[at] = first_x[r] + _SET_BITS[mask[r], k], r
    t = (th[source] << 12) | tl[source]
    t, reordered = _monotonic(t, last_t)
    n = len(words)
    new_state = np.array([
        end_high,
        int(payload[is_tl][-1]) if is_tl.any() else time_low,
        int(payload[is_y][-1] & 0x7FF) if is_y.any() else y_state,
        end_base if n else base_state, end_pol if n else pol_state,
        int(t[-1]) if len(t) else last_t, low_after_high,
    ], np.int64)
    return (x.astype(np.int16), row[source].astype(np.int16), t, polarity[source].astype(np.int8), new_state,
            reordered)


class _TimeWentBack(Exception):
    """A decoder's record ``index`` (in its chunk), holding the time word ``stamp``, reads as
    ``behind`` µs earlier than a record before it, more than the format tolerates; the reader
    names the file and the byte offset."""

    def __init__(self, index: int, stamp: int, behind: int) -> None:
        super().__init__(index, stamp, behind)
        self.index, self.stamp, self.behind = index, stamp, behind


def _decode_dat(records: np.ndarray, state: np.ndarray):
    """records: (N, 2) uint32 (time, packed address). Returns (x, y, t, p, state, reordered).

    The 32-bit µs counter wraps every ~71.6 min. Each record's step from the one before is read
    modulo 2^32 as a signed number (serial-number arithmetic, RFC 1982): a counter that passed
    0xFFFFFFFF steps forward by a little, which is a wrap; a step back (0xFFFFFFF0 after 2000,
    or 900 after 1000) is a time going backwards, never a wrap. Going back by at most
    ``DAT_REORDER_TOLERANCE_US`` behind the latest time is a late-stamped event (given that
    time, counted); further raises :class:`_TimeWentBack`.
    """
    time, last_t = (int(v) for v in state)
    stamps = records[:, 0].astype(np.int64)
    if len(stamps) == 0:
        return (np.zeros(0, np.int16), np.zeros(0, np.int16), np.zeros(0, np.int64), np.zeros(0, np.int8),
                state.copy(), 0)
    period = np.int64(1) << 32
    previous = np.concatenate([[time % period if time >= 0 else stamps[0]], stamps[:-1]])
    steps = (stamps - previous + period // 2) % period - period // 2
    full = (time if time >= 0 else stamps[0]) + np.cumsum(steps)
    latest = np.maximum.accumulate(np.maximum(full, last_t))
    behind = np.flatnonzero(latest - full > DAT_REORDER_TOLERANCE_US)
    if len(behind):
        i = int(behind[0])
        raise _TimeWentBack(i, int(stamps[i]), int(latest[i] - full[i]))
    t, reordered = _monotonic(full, last_t)
    data = records[:, 1]
    x = (data & 0x3FFF).astype(np.int16)
    y = ((data >> 14) & 0x3FFF).astype(np.int16)
    p = (((data >> 28) & 0xF) > 0).astype(np.int8)
    return x, y, t, p, np.array([full[-1], t[-1]], np.int64), reordered


# ---------------------------------------------------------------------------------------------


def _given_or_header(path: Path, given, header: tuple[int, int] | None, lacking: str) -> tuple[int, int] | None:
    """The sensor size a reader opens with: ``given`` (height, width) over the header's; "auto":
    the header's, or None (picked from the events once they are indexed); neither: FormatError
    naming the file and how to give the size."""
    if isinstance(given, str):
        if given != "auto":
            raise ValueError(f"{path}: sensor_size must be (height, width) or 'auto', got {given!r}")
        return header
    size = given if given is not None else header
    if size is None:
        raise FormatError(f"{path}: {lacking}; {SENSOR_SIZE_HINT}")
    return int(size[0]), int(size[1])


def _index_root(index_dir) -> Path | None:
    if index_dir is not None:
        return Path(index_dir)
    root = cache_root()
    return None if root is None else root / "prophesee-index"


class _ChunkedReader(EventReader):
    """A file of fixed-size words decoded a chunk at a time through a cached time index
    (module docstring). Subclasses set the word layout and the decoder."""

    layout = "prophesee"
    _word_dtype: np.dtype
    _words_per_item = 1  # array items per word (DAT: 2 uint32 per record)
    _state_names: tuple[str, ...]

    def _setup(self, path: Path, data_offset: int, chunk_words: int, index_dir, validate: bool) -> None:
        self.path = path
        self.name = path.stem
        self.validate = validate
        self._data_offset = int(data_offset)
        self._chunk_words = int(chunk_words)
        self._word_bytes = np.dtype(self._word_dtype).itemsize * self._words_per_item
        size = path.stat().st_size
        data_bytes = size - self._data_offset
        if data_bytes % self._word_bytes:
            raise FormatError(
                f"{path}: truncated: {data_bytes} bytes of event data after the header is not a whole "
                f"number of {self._word_bytes}-byte words (the file ends {data_bytes % self._word_bytes} "
                "bytes into a word)"
            )
        self._num_words = data_bytes // self._word_bytes
        self._file = open(path, "rb")
        self._decoded: OrderedDict[int, tuple] = OrderedDict()
        self._load_or_build_index(_index_root(index_dir))
        counts = np.diff(self._first_event)
        self.num_events = int(self._first_event[-1])
        self._chunk_t_last = self._t_last  # -1 for chunks without events before any with
        nonempty = np.flatnonzero(counts > 0)
        if len(nonempty):
            self._t_start = int(self._decode_chunk(int(nonempty[0]))[2][0])
            self._t_end = int(self._t_last[-1]) + 1
        else:
            self._t_start, self._t_end = 0, 1
        if self._t_end - self._t_start > MAX_SPAN_US:
            raise FormatError(
                f"{path}: the event times span [{self._t_start}, {self._t_end}) us, more than "
                f"{MAX_SPAN_US // 3_600_000_000} h; corrupt time words?"
            )
        if self.reordered_events:
            warnings.warn(f"{path}: {self.reordered_events} events were stamped earlier than an event before "
                          "them and were given that earlier time", stacklevel=3)

    # --- the time index -------------------------------------------------------------------
    def _index_key(self) -> str:
        st = self.path.stat()
        ident = f"{_INDEX_VERSION}|{self.path.resolve()}|{st.st_size}|{st.st_mtime_ns}|{self._chunk_words}|{type(self).__name__}"
        return hashlib.sha1(ident.encode()).hexdigest()[:16]

    def _load_or_build_index(self, root: Path | None) -> None:
        """The time index from the cache, else built and cached; either way the geometry is
        checked against it (a cached index holds each chunk's largest x and y)."""
        cached = None if root is None else root / f"{self.name}-{self._index_key()}.npz"
        if cached is not None and cached.exists():
            try:
                with np.load(cached) as z:
                    self._states, self._first_event = z["states"], z["first_event"]
                    self._t_last, self.reordered_events = z["t_last"], int(z["reordered"])
                    self._chunk_max = z["chunk_max"]
                self.index_path = cached
            except (OSError, KeyError, ValueError):
                cached.unlink(missing_ok=True)  # unreadable cache: build again
            else:
                self._check_geometry()
                return
        self._build_index()
        self._check_geometry()  # before caching: a refused file leaves nothing behind
        self.index_path = None
        if cached is not None:
            try:
                cached.parent.mkdir(parents=True, exist_ok=True)
                fd, tmp = tempfile.mkstemp(prefix=cached.stem, suffix=".tmp.npz", dir=cached.parent)
                os.close(fd)
                try:
                    np.savez(tmp, states=self._states, first_event=self._first_event, t_last=self._t_last,
                             reordered=np.int64(self.reordered_events), chunk_max=self._chunk_max)
                    os.replace(tmp, cached)
                    self.index_path = cached
                finally:
                    Path(tmp).unlink(missing_ok=True)
            except OSError as err:
                warnings.warn(f"{self.path}: could not cache the time index in {cached.parent}: {err}", stacklevel=4)

    def _build_index(self) -> None:
        n_chunks = -(-self._num_words // self._chunk_words)
        states = np.empty((n_chunks + 1, len(self._state_names)), np.int64)
        first = np.zeros(n_chunks + 1, np.int64)
        t_last = np.empty(n_chunks, np.int64)
        chunk_max = np.full((n_chunks, 2), -1, np.int64)  # each chunk's largest x and y (-1: no events)
        state = np.full(len(self._state_names), -1, np.int64)
        reordered = 0
        last_t = -1
        for k in range(n_chunks):
            states[k] = state
            x, y, t, p, state, moved = self._decode(k, state)
            if len(x):
                chunk_max[k] = int(x.max()), int(y.max())
            reordered += moved
            first[k + 1] = first[k] + len(t)
            last_t = int(t[-1]) if len(t) else last_t
            t_last[k] = last_t
        states[n_chunks] = state
        self._states, self._first_event, self._t_last = states, first, t_last
        self._chunk_max = chunk_max
        self.reordered_events = reordered

    def _check_geometry(self) -> None:
        """Every event inside the sensor, from the index's per-chunk maxima (so a cached index,
        made at another geometry, is checked too): FormatError naming the file and the chunk.
        With ``sensor_size="auto"`` on a file without geometry, the size is picked here first
        (``envs.readers._common.auto_sensor_size``, from the index's maxima)."""
        if self.sensor_size is None:
            top = self._chunk_max.max(axis=0) if len(self._chunk_max) else (-1, -1)
            self.sensor_size = auto_sensor_size(int(top[0]), int(top[1]), self.path)
        if not self.validate:
            return
        h, w = self.sensor_size
        for axis, (name, limit) in enumerate((("x", w), ("y", h))):
            bad = np.flatnonzero(self._chunk_max[:, axis] >= limit)
            if len(bad):
                k = int(bad[0])
                raise FormatError(
                    f"{self.path}: event {name}={int(self._chunk_max[k, axis])} outside the {h}x{w} sensor (height x width) "
                    f"in the words from byte {self._data_offset + k * self._chunk_words * self._word_bytes}; "
                    f"wrong geometry in the header? {SENSOR_SIZE_HINT}"
                )

    # --- decoding -------------------------------------------------------------------------
    def _decode(self, k: int, state: np.ndarray):
        """The decoder on chunk ``k`` from ``state``; a time going backwards raises FormatError
        naming the file and the record's byte offset."""
        try:
            return self._decoder(self._read_words(k), state)
        except _TimeWentBack as back:
            offset = self._data_offset + (k * self._chunk_words + back.index) * self._word_bytes
            raise FormatError(
                f"{self.path}: the event at byte {offset} is stamped {back.stamp} us (0x{back.stamp:08X}), {back.behind} us "
                f"before an event ahead of it: more than the {DAT_REORDER_TOLERANCE_US} us tolerated, and no wrap of "
                "the time counter; the record is corrupt"
            ) from None

    def _read_words(self, k: int) -> np.ndarray:
        start = k * self._chunk_words
        count = min(self._chunk_words, self._num_words - start)
        self._file.seek(self._data_offset + start * self._word_bytes)
        raw = self._file.read(count * self._word_bytes)
        if len(raw) != count * self._word_bytes:
            raise FormatError(f"{self.path}: the file shrank while being read (byte {self._file.tell()})")
        words = np.frombuffer(raw, self._word_dtype)
        return words.reshape(-1, self._words_per_item) if self._words_per_item > 1 else words

    def _decode_chunk(self, k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        hit = self._decoded.get(k)
        if hit is not None:
            self._decoded.move_to_end(k)
            return hit
        x, y, t, p, _, _ = self._decode(k, self._states[k])
        hit = (x, y, t, np.where(p > 0, 1, -1).astype(np.int8))
        self._decoded[k] = hit
        while len(self._decoded) > 3:
            self._decoded.popitem(last=False)
        return hit

    # --- EventReader ----------------------------------------------------------------------
    def events_range(self, i_start: int, i_end: int) -> Events:
        i_start = max(0, int(i_start))
        i_end = min(self.num_events, int(i_end))
        if i_end <= i_start:
            return Events.empty(self.sensor_size)
        k0 = int(np.searchsorted(self._first_event, i_start, side="right")) - 1
        k1 = int(np.searchsorted(self._first_event, i_end, side="left"))
        parts = []
        for k in range(k0, k1):
            lo = max(i_start, int(self._first_event[k])) - int(self._first_event[k])
            hi = min(i_end, int(self._first_event[k + 1])) - int(self._first_event[k])
            if hi > lo:
                x, y, t, p = self._decode_chunk(k)
                parts.append(Events(x[lo:hi], y[lo:hi], t[lo:hi], p[lo:hi], self.sensor_size))
        return parts[0] if len(parts) == 1 else Events.concatenate(parts)

    def index_at(self, t_us: int) -> int:
        k = int(np.searchsorted(self._t_last, int(t_us), side="left"))  # first chunk reaching t_us
        if k >= len(self._t_last):
            return self.num_events
        t = self._decode_chunk(k)[2]
        return int(self._first_event[k]) + int(np.searchsorted(t, int(t_us), side="left"))

    def time_of(self, index: int) -> int:
        k = int(np.searchsorted(self._first_event, int(index), side="right")) - 1
        return int(self._decode_chunk(k)[2][int(index) - int(self._first_event[k])])

    def close(self) -> None:
        if getattr(self, "_file", None) is not None:
            self._file.close()
            self._file = None
        self._decoded = OrderedDict()

    def __del__(self) -> None:
        try:
            self.close()
        except Exception:
            pass


class PropheseeRawReader(_ChunkedReader):
    """A Prophesee RAW file (EVT 2.0 or EVT 3.0; module docstring).

    sensor_size: (height, width), needed only when the header gives no geometry (given, it
    replaces the header's); "auto": the header's, else the smallest known sensor holding every
    event (``envs.readers._common.KNOWN_SENSORS``), with a warning naming it.
    chunk_words: words decoded at a time (memory: about 12 events per EVT 3.0 word at worst).
    index_dir: where the time index is cached (default ``$EVFLOW_CACHE/prophesee-index``).
    validate: check every event lies inside the sensor while building the index.

    Attributes: ``header`` (:class:`RawHeader`: format, geometry, camera keys),
    ``reordered_events``, ``index_path`` (the cached index, or None).
    """

    layout = "prophesee-raw"

    def __init__(
        self,
        path: str | os.PathLike,
        *,
        sensor_size: tuple[int, int] | str | None = None,
        chunk_words: int | None = None,
        index_dir: str | os.PathLike | None = None,
        validate: bool = True,
    ) -> None:
        path = Path(path)
        if not path.exists():
            raise FileNotFoundError(f"{path}: no such file")
        self.header = read_raw_header(path)
        self.sensor_size = _given_or_header(path, sensor_size, self.header.sensor_size, "the RAW header gives no geometry")
        if self.header.format == "EVT2":
            self._word_dtype, self._state_names, self._decoder = np.dtype("<u4"), _EVT2_STATE, _decode_evt2
        else:
            self._word_dtype, self._state_names, self._decoder = np.dtype("<u2"), _EVT3_STATE, _decode_evt3
        self._setup(path, self.header.data_offset, chunk_words or (1 << 19 if self.header.format == "EVT2" else 1 << 18),
                    index_dir, validate)

    @property
    def format(self) -> str:
        return self.header.format


class PropheseeDatReader(_ChunkedReader):
    """A Prophesee DAT file of CD events (module docstring).

    sensor_size: (height, width), needed only when the header has no ``% Width``/``% Height``;
    "auto" as for RAW. chunk_words: records decoded at a time; index_dir, validate: as for RAW.
    Attribute ``header``: the header's keys. ``__init__`` opens as the RAW reader's does (the
    same options and checks), then reads its own header.
    """

    layout = "prophesee-dat"
    _word_dtype = np.dtype("<u4")
    _words_per_item = 2
    _state_names = _DAT_STATE

    def __init__(
        self,
        path: str | os.PathLike,
        *,
        sensor_size: tuple[int, int] | str | None = None,
        chunk_words: int = 1 << 18,
        index_dir: str | os.PathLike | None = None,
        validate: bool = True,
    ) -> None:
        path = Path(path)
        if not path.exists():
            raise FileNotFoundError(f"{path}: no such file")
        with open(path, "rb") as fh:
            head = fh.read(_HEADER_LIMIT)
        lines, offset = _header_lines(path, head) if head.startswith(b"%") else ([], 0)
        self.header = {}
        for line in lines:
            key, _, value = line.partition(" ")
            self.header[key.strip()] = value.strip()
        if len(head) < offset + 2:
            raise FormatError(f"{path}: truncated: the DAT file ends before its event type and size bytes")
        ev_type, ev_size = head[offset], head[offset + 1]
        if ev_type not in DAT_EVENT_TYPES:
            what = "external-trigger events (EventExtTrigger)" if ev_type == _DAT_TRIGGER else "an unknown event type"
            raise FormatError(
                f"{path}: DAT event type 0x{ev_type:02X} is {what}; this reader reads CD events "
                f"(types {', '.join(f'0x{k:02X} {v}' for k, v in DAT_EVENT_TYPES.items())})"
            )
        if ev_size != 8:
            raise FormatError(f"{path}: DAT event size {ev_size} bytes; CD events are 8 bytes")
        header_size = None  # read only when no size is given: a given size stands for a bad header's
        if sensor_size in (None, "auto") and "Height" in self.header and "Width" in self.header:
            header_size = _header_size(path, "'% Height' / '% Width' lines", self.header["Height"], self.header["Width"])
        self.sensor_size = _given_or_header(path, sensor_size, header_size, "the DAT header has no '% Width'/'% Height'")
        self._decoder = _decode_dat
        self._setup(path, offset + 2, chunk_words, index_dir, validate)
