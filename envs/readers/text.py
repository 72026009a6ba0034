"""Event text files, as in the Event Camera Dataset (ECD, Mueggler et al. 2017): ``events.txt``.

Layout read: one event per line, ``t x y p`` separated by spaces: t in seconds (float), x
column, y row, p in {0, 1} (or -1/+1). Leading header lines that do not hold four numbers
are skipped; a leading ``width height`` line (the rpg_e2vid convention) gives the sensor size.
Blank lines after the header are an error (they would break the line index), and so are a
file whose first lines are not text or hold no ``t x y p`` line (e.g. a binary file forced as
text), a NaN or infinite time, coordinates that are not whole non-negative numbers (10.7 is
not truncated to 10) or that reach ``MAX_SENSOR_SIDE`` (x = 70000 is not stored as 4464), a
polarity other than 0, 1 (or -1), and a time more than ``MAX_SPAN_US`` (24 h) after the first
event's; each names the line. A UTF-8 byte-order mark before the first line is skipped.

Sensor size: the ``sensor_size`` argument, else the header line, else the first frame's size
when ``images.txt`` lies beside the file, else the ECD camera (DAVIS240C, 180 x 240) when all
coordinates fit it, else the largest coordinates + 1. ``sensor_size="auto"`` takes the header
or the frames too, else the smallest known sensor holding every event, with a warning naming it
(``envs.readers._common.auto_sensor_size``).

Streaming: opening makes one pass over the file (a chunk at a time) that records the byte
offset and first time of every block of ``block_lines`` lines; a window then reads and parses
only the blocks it touches (the last two parsed blocks are kept). Times are integer µs as
written (``rint(t * 1e6)``, no origin shift). Frames: ECD's ``images.txt`` (``t path`` lines)
beside the file, read with Pillow when asked for.
"""

from __future__ import annotations

import io
import os
from collections import OrderedDict
from pathlib import Path

import numpy as np

from envs.events import MAX_SENSOR_SIDE, MAX_SPAN_US, Events
from envs.readers._common import auto_sensor_size, check_finite, check_pixel_coordinates
from envs.readers.base import EventReader, FormatError

__all__ = ["TextReader", "ECD_SENSOR_SIZE"]

ECD_SENSOR_SIZE = (180, 240)
_READ_BYTES = 1 << 23
_BOM = b"\xef\xbb\xbf"


def _parse(body: bytes, path: Path, first_line: int) -> np.ndarray:
    try:
        rows = np.loadtxt(io.BytesIO(body), dtype=np.float64, ndmin=2, comments=None)
    except ValueError as err:
        raise FormatError(f"{path}: malformed event line near line {first_line} (expected 't x y p'): {err}") from None
    if rows.size and rows.shape[1] != 4:
        raise FormatError(f"{path}: lines from line {first_line} have {rows.shape[1]} columns, expected 4 ('t x y p')")
    return rows.reshape(-1, 4)


class TextReader(EventReader):
    """A ``t x y p`` event text file, streamed (module docstring for the conventions).

    sensor_size: (height, width), overrides detection; "auto": module docstring. time_unit: "s" (ECD) or "us".
    block_lines: lines per index block (memory per cached block: 32 bytes per line).
    """

    layout = "ecd-text"

    def __init__(
        self,
        path: str | os.PathLike,
        *,
        sensor_size: tuple[int, int] | str | None = None,
        time_unit: str = "s",
        block_lines: int = 1 << 15,
        validate: bool = True,
    ) -> None:
        self.path = Path(path)
        if not self.path.exists():
            raise FileNotFoundError(f"{self.path}: no such file")
        if time_unit not in ("s", "us"):
            raise ValueError(f"time_unit must be 's' or 'us', got {time_unit!r}")
        self.name = self.path.parent.name if self.path.name == "events.txt" else self.path.stem
        self._scale = 1e6 if time_unit == "s" else 1.0
        self.block_lines = int(block_lines)
        self.validate = validate
        self._cache: OrderedDict[int, np.ndarray] = OrderedDict()
        header_size, data_start = self._read_header()
        self._data_start = data_start
        self._index()
        self._frames_t, self._frame_paths = self._find_frames()
        auto = isinstance(sensor_size, str)
        if auto and sensor_size != "auto":
            raise ValueError(f"{self.path}: sensor_size must be (height, width) or 'auto', got {sensor_size!r}")
        if sensor_size is None or auto:
            sensor_size = header_size
        if sensor_size is None and self._frame_paths:
            from PIL import Image

            with Image.open(self._frame_paths[0]) as im:
                sensor_size = (im.height, im.width)
        if sensor_size is None and auto:
            sensor_size = auto_sensor_size(self._max_x, self._max_y, self.path)
        if sensor_size is None:
            fits = self._max_x < ECD_SENSOR_SIZE[1] and self._max_y < ECD_SENSOR_SIZE[0]
            sensor_size = ECD_SENSOR_SIZE if fits else (self._max_y + 1, self._max_x + 1)
        self.sensor_size = (int(sensor_size[0]), int(sensor_size[1]))
        if self.num_events and (self._max_x >= self.sensor_size[1] or self._max_y >= self.sensor_size[0] or self._min_xy < 0):
            raise FormatError(
                f"{self.path}: event coordinates span x <= {self._max_x}, y <= {self._max_y} (min "
                f"{self._min_xy}), outside the {self.sensor_size[0]}x{self.sensor_size[1]} sensor (height x width)"
            )

    def _to_us(self, t: np.ndarray) -> np.ndarray:
        return np.rint(t * self._scale).astype(np.int64)

    def _read_header(self) -> tuple[tuple[int, int] | None, int]:
        """Skip leading lines that are not 't x y p'; a 'width height' line gives the size.

        A header line that is not printable text, or 16 lines without an event line, raise
        FormatError: such a file is not an event text file (a binary file would otherwise read
        as a header and no events)."""
        size, offset = None, 0
        self._header_lines = 0
        with open(self.path, "rb") as fh:
            if fh.read(3) == _BOM:  # a UTF-8 byte-order mark (Windows editors): not part of line 1
                offset = len(_BOM)
            else:
                fh.seek(0)
            for k in range(17):
                line = fh.readline()
                if not line:
                    break
                if k == 16:
                    raise FormatError(f"{self.path}: no 't x y p' event line in the first 16 lines; not an event text file")
                try:
                    text = line.decode("utf-8")
                except UnicodeDecodeError:
                    text = None
                if text is None or not text.lstrip("\ufeff").rstrip("\r\n").replace("\t", " ").isprintable():
                    raise FormatError(
                        f"{self.path}: line {k + 1} is not text (binary data?); an event text file holds "
                        "'t x y p' lines after an optional header"
                    )
                tokens = line.split()
                if len(tokens) == 4 and not line.lstrip().startswith(b"#"):
                    try:
                        [float(v) for v in tokens]
                        self._header_lines = k
                        break
                    except ValueError:
                        pass
                if len(tokens) == 2 and size is None:
                    try:
                        width, height = int(tokens[0]), int(tokens[1])
                        size = (height, width)
                    except ValueError:
                        pass
                offset += len(line)
        return size, offset

    def _parse_lines(self, body: bytes, count: int, n: int, first_t: int | None,
                     last_t: int | None) -> tuple[np.ndarray, np.ndarray]:
        """The ``count`` lines of ``body`` (events ``n`` on) as rows (t, x, y, p) and their times
        in µs, checked: finite times, pixel coordinates, values (``first_t``: the file's first
        time in µs, None before it is read) and, with ``validate``, times in order after
        ``last_t`` (the previous lines' last time)."""
        rows = _parse(body, self.path, n + 1)
        if len(rows) != count:
            raise FormatError(f"{self.path}: could not split the lines near event {n + 1} into 't x y p'")
        check_finite(rows[:, 0], str(self.path), "t", n)
        for column, field in ((1, "x"), (2, "y")):
            check_pixel_coordinates(rows[:, column], str(self.path), field, n)
        self._check_values(rows, n, None if first_t is None else first_t / self._scale)
        t = self._to_us(rows[:, 0])
        if self.validate:
            dt = np.diff(t)
            if (dt < 0).any() or (last_t is not None and len(t) and t[0] < last_t):
                i = 0 if last_t is not None and t[0] < last_t else int(np.flatnonzero(dt < 0)[0]) + 1
                raise FormatError(f"{self.path}: field 't' decreases at event {n + i} (line {n + i + 1} of the events)")
        return rows, t

    def _index(self) -> None:
        """One pass: block offsets and first times, event count, coordinate range, time order."""
        b = self.block_lines
        offsets, block_t = [], []
        n, last_t, first_t = 0, None, None
        max_x = max_y = -1
        min_xy = 0
        with open(self.path, "rb") as fh:
            fh.seek(self._data_start)
            pos, carry = self._data_start, b""
            while True:
                chunk = fh.read(_READ_BYTES)
                buf = carry + chunk
                if not chunk:
                    if not buf.strip():
                        break
                    if not buf.endswith(b"\n"):
                        buf += b"\n"
                cut = buf.rfind(b"\n") + 1
                if cut == 0:
                    carry = buf
                    continue
                body, carry = buf[:cut], buf[cut:]
                nl = np.flatnonzero(np.frombuffer(body, np.uint8) == 10)
                starts = np.concatenate([[0], nl[:-1] + 1])
                length = nl - starts
                blank = (length == 0) | ((length == 1) & (np.frombuffer(body, np.uint8)[starts] == 13))
                if blank.any():
                    tail = blank.all() and not chunk  # trailing blank lines at the end of file
                    if not tail:
                        line = n + int(np.flatnonzero(blank)[0]) + 1
                        raise FormatError(f"{self.path}: blank line after event {line - 1} (the line index needs one event per line)")
                    break
                rows, t = self._parse_lines(body, len(starts), n, first_t, last_t)
                if first_t is None and len(t):
                    first_t = int(t[0])
                sel = np.flatnonzero((n + np.arange(len(t))) % b == 0)
                offsets.extend((pos + starts[sel]).tolist())
                block_t.extend(t[sel].tolist())
                if len(t):
                    last_t = int(t[-1])
                    max_x = max(max_x, int(rows[:, 1].max()))
                    max_y = max(max_y, int(rows[:, 2].max()))
                    min_xy = min(min_xy, int(rows[:, 1:3].min()))
                n += len(t)
                pos += cut
                if not chunk:
                    break
        self._offsets = np.asarray(offsets + [pos], np.int64)
        self._block_t = np.asarray(block_t, np.int64)
        self.num_events = n
        self._max_x, self._max_y, self._min_xy = max_x, max_y, min_xy
        self._t_start = int(self._block_t[0]) if n else 0
        self._t_end = (last_t + 1) if last_t is not None else 1

    def _check_values(self, rows: np.ndarray, n: int, first_t: float | None) -> None:
        """Values that parse but cannot be right, refused naming the line: a coordinate beyond
        the largest sensor (``MAX_SENSOR_SIDE``), a polarity other than 0, 1 (or -1), a time
        more than ``MAX_SPAN_US`` after the first event's (or one whose µs overflow int64).
        rows: (N, 4) float64 t x y p of events n.. ; first_t: the first event's time in the
        file's unit (None: these rows start the file)."""
        if not len(rows):
            return
        unit = "s" if self._scale == 1e6 else "us"
        origin = rows[0, 0] if first_t is None else first_t
        span = MAX_SPAN_US / self._scale
        checks = [
            (rows[:, 1] >= MAX_SENSOR_SIDE, lambda r: f"x = {r[1]:.17g} is beyond the largest sensor side, {MAX_SENSOR_SIDE} pixels"),
            (rows[:, 2] >= MAX_SENSOR_SIDE, lambda r: f"y = {r[2]:.17g} is beyond the largest sensor side, {MAX_SENSOR_SIDE} pixels"),
            (~np.isin(rows[:, 3], (0.0, 1.0, -1.0)), lambda r: f"polarity p = {float(r[3])!r}; expected 0 or 1 (or -1 / +1)"),
            ((np.abs(rows[:, 0]) * self._scale > 2.0**62) | (rows[:, 0] - origin > span),
             lambda r: f"t = {float(r[0])!r} {unit} is more than {span:g} {unit} ({MAX_SPAN_US // 3_600_000_000} h) "
                       f"after the first event's {float(origin)!r} {unit}; corrupt time?"),
        ]
        for bad, message in checks:
            if bad.any():
                i = int(np.flatnonzero(bad)[0])
                raise FormatError(f"{self.path}: line {self._header_lines + n + i + 1} (event {n + i}): {message(rows[i])}")

    def _find_frames(self):
        listing = self.path.with_name("images.txt")
        if not listing.exists():
            return None, []
        times, paths = [], []
        for line in listing.read_text().splitlines():
            parts = line.split()
            if len(parts) >= 2 and not line.startswith("#"):
                times.append(float(parts[0]))
                paths.append(self.path.parent / parts[1])
        return self._to_us(np.asarray(times, np.float64)), paths

    def _block(self, k: int) -> np.ndarray:
        rows = self._cache.get(k)
        if rows is None:
            with open(self.path, "rb") as fh:
                fh.seek(int(self._offsets[k]))
                body = fh.read(int(self._offsets[k + 1] - self._offsets[k]))
            rows = _parse(body, self.path, k * self.block_lines + 1)
            self._cache[k] = rows
            if len(self._cache) > 2:
                self._cache.popitem(last=False)
        return rows

    # -- the reader interface ----------------------------------------------------------------
    def index_at(self, t_us: int) -> int:
        j = int(np.searchsorted(self._block_t, int(t_us), side="left"))
        if j == 0:
            return 0
        t = self._to_us(self._block(j - 1)[:, 0])
        return (j - 1) * self.block_lines + int(np.searchsorted(t, int(t_us), side="left"))

    def events_range(self, i_start: int, i_end: int) -> Events:
        i_start, i_end = max(0, int(i_start)), min(self.num_events, int(i_end))
        if i_end <= i_start:
            return Events.empty(self.sensor_size)
        b = self.block_lines
        parts = [self._block(k) for k in range(i_start // b, (i_end - 1) // b + 1)]
        rows = parts[0] if len(parts) == 1 else np.concatenate(parts)
        rows = rows[i_start - (i_start // b) * b : i_end - (i_start // b) * b]
        return Events.create(
            rows[:, 1].astype(np.int64), rows[:, 2].astype(np.int64), self._to_us(rows[:, 0]),
            rows[:, 3].astype(np.int64), self.sensor_size,
            source=f"{self.path} (events {i_start}..{i_end})", validate=self.validate,
        )

    def time_of(self, index: int) -> int:
        k = int(index) // self.block_lines
        return int(self._to_us(self._block(k)[int(index) - k * self.block_lines, 0:1])[0])

    def frame_timestamps(self) -> np.ndarray | None:
        return self._frames_t

    def frame(self, index: int) -> np.ndarray:
        if not self._frame_paths:
            return super().frame(index)
        from PIL import Image

        with Image.open(self._frame_paths[int(index)]) as im:
            return np.asarray(im.convert("L"))
