"""AEDAT4 recordings (iniVation DAVIS / DVXplorer cameras, DV software) through the ``aedat``
package (the project's optional ``aedat`` extra: ``pip install evflow-gym[aedat]``).

API used (``aedat`` 2.3, documented in its README): ``aedat.Decoder(path)`` is an iterator of
packets with ``id_to_stream() -> {stream_id: {"type": "events" | "frame" | "imus" | "triggers",
"width", "height"}}``; each packet is a dict with ``"stream_id"`` and one of ``"events"`` (a
structured array with fields t (u8, µs), x (u2), y (u2), on (bool)), ``"frame"`` (a dict with
``t``, ``format`` ("L", "RGB", "RGBA", or "I;16"), ``width``, ``height``, ``offset_x``,
``offset_y``, ``pixels`` (H, W[, C]) uint8 or uint16), ``"imus"`` or ``"triggers"``.

AEDAT4 is a packet stream without a time index, so the reader decodes the file once, packet by
packet, into a temporary project h5 file (``cache_dir``, default the system temp folder;
removed on ``close``) and streams windows from there: memory stays one packet deep. Times are
the camera's absolute µs. Frames (if the file has a frame stream) are converted to (H, W) uint8
gray (16-bit samples >> 8, colour averaged over channels) and placed at their offset.

Errors name the user's file, never the decoded copy: a file that does not start with the AEDAT4
line, a header or packet the decoder cannot read (a cut or damaged file), no polarity event
stream, events or frames going back in time. A failed or interrupted open removes the copy.
"""

from __future__ import annotations

import itertools
import os
import tempfile
from pathlib import Path

import numpy as np

from envs.events import EventError, Events
from envs.readers._common import missing_extra
from envs.readers.base import EventReader, FlowGT, FormatError
from envs.readers.h5 import H5Reader, H5Writer

__all__ = ["AedatReader", "import_aedat"]

MAGIC = b"#!AER-DAT4.0\r\n"  # the first line of every AEDAT 4.0 file


def import_aedat():
    """The ``aedat`` module, or an ImportError saying to install the extra."""
    try:
        import aedat
    except ImportError:
        raise missing_extra("aedat", "aedat", "Reading AEDAT4 files") from None
    return aedat


def _check_magic(path: Path) -> None:
    """A FormatError naming ``path`` unless it starts with the AEDAT4 header line (the decoder's
    own message for other files is a bare "invalid utf-8 sequence" or "failed to fill whole
    buffer")."""
    with open(path, "rb") as f:
        head = f.read(len(MAGIC))
    if head != MAGIC:
        if not head:
            kind = "an empty file"
        elif MAGIC.startswith(head):
            kind = f"cut short: {len(head)} bytes"
        elif head.startswith(b"#!AER-DAT"):
            kind = "an AEDAT file of another version"
        else:
            kind = "not an AEDAT4 file"
        raise FormatError(
            f"{path}: {kind}: it starts with {head!r}, an AEDAT4 file starts with {MAGIC!r}"
        )


def _describe(streams: dict) -> str:
    """The decoder's streams in words: "stream 1: frame 346x260, stream 2: imus"."""
    if not streams:
        return "no streams"
    return ", ".join(
        f"stream {k}: {s.get('type')}" + (f" {s['width']}x{s['height']}" if "width" in s else "")
        for k, s in sorted(streams.items())
    )


def _gray(frame: dict, sensor_size: tuple[int, int]) -> np.ndarray:
    pixels = np.asarray(frame["pixels"])
    if pixels.dtype == np.uint16:
        pixels = (pixels >> 8).astype(np.uint8)
    if pixels.ndim == 3:
        pixels = np.rint(pixels[:, :, :3].astype(np.float32).mean(axis=2)).astype(np.uint8)
    h, w = sensor_size
    if pixels.shape == (h, w):
        return pixels.astype(np.uint8)
    out = np.zeros((h, w), np.uint8)
    oy, ox = int(frame.get("offset_y", 0)), int(frame.get("offset_x", 0))
    ph, pw = min(pixels.shape[0], h - oy), min(pixels.shape[1], w - ox)
    out[oy : oy + ph, ox : ox + pw] = pixels[:ph, :pw]
    return out


class AedatReader(EventReader):
    """An AEDAT4 file (module docstring). stream_id: which event stream (default: the first).
    cache_dir: where the temporary decoded copy goes."""

    layout = "aedat4"

    def __init__(
        self,
        path: str | os.PathLike,
        *,
        stream_id: int | None = None,
        cache_dir: str | os.PathLike | None = None,
        validate: bool = True,
    ) -> None:
        self.path = Path(path)
        if not self.path.exists():
            raise FileNotFoundError(f"{self.path}: no such file")
        aedat = import_aedat()
        self.name = self.path.stem
        self._inner: H5Reader | None = None
        _check_magic(self.path)
        try:
            decoder = aedat.Decoder(str(self.path))
            streams = decoder.id_to_stream()
        except (RuntimeError, OSError, ValueError) as err:
            raise FormatError(
                f"{self.path}: the AEDAT4 header cannot be read ({err}); the file is cut short or damaged"
            ) from None
        event_ids = sorted(k for k, s in streams.items() if s.get("type") == "events")
        if stream_id is None:
            if not event_ids:
                raise FormatError(
                    f"{self.path}: no polarity event stream (EVTS); the file holds {_describe(streams)}"
                )
            stream_id = event_ids[0]
        elif stream_id not in event_ids:
            raise FormatError(
                f"{self.path}: stream {stream_id} is not a polarity event stream; the file holds "
                f"{_describe(streams)}"
            )
        info = streams[stream_id]
        self.sensor_size = (int(info["height"]), int(info["width"]))
        frame_ids = sorted(k for k, s in streams.items() if s.get("type") == "frame")
        if cache_dir is not None:
            Path(cache_dir).mkdir(parents=True, exist_ok=True)  # a cache folder that does not exist yet
        fd, tmp = tempfile.mkstemp(prefix=f"{self.name}-", suffix=".evflow.h5", dir=cache_dir)
        os.close(fd)
        self._cache_path = Path(tmp)
        try:
            writer = H5Writer(self._cache_path, self.sensor_size, name=self.name,
                              provenance={"source": str(self.path), "format": "aedat4"})
            with writer:
                self._decode(decoder, writer, stream_id, frame_ids[0] if frame_ids else None, validate)
            self._inner = H5Reader(self._cache_path, validate=validate)
        except BaseException:  # Ctrl-C included: no decoded copy survives a failed open
            self._cache_path.unlink(missing_ok=True)
            raise
        finally:
            decoder = None  # the aedat README: drop the decoder to release the file
        self.num_events = self._inner.num_events

    def _decode(self, decoder, writer: H5Writer, stream_id: int, frame_id: int | None, validate: bool) -> None:
        """Every packet of ``decoder`` into ``writer``: the events of ``stream_id`` and the
        frames of ``frame_id``, each checked to go forward in time (an error names this file,
        the stream and the packet, not the temporary copy)."""
        last_t: int | None = None
        last_frame_t: int | None = None
        num_events = 0
        packets = iter(decoder)
        for number in itertools.count():
            try:
                packet = next(packets)
            except StopIteration:
                return
            except (RuntimeError, OSError, ValueError) as err:
                raise FormatError(
                    f"{self.path}: AEDAT4 packet {number} cannot be read ({err}) after "
                    f"{num_events} events; the file is cut short or damaged"
                ) from None
            sid = packet.get("stream_id")
            where = f"{self.path} (stream {sid}, packet {number})"
            if sid == stream_id and "events" in packet:
                ev = packet["events"]
                if len(ev) == 0:
                    continue
                t = ev["t"].astype(np.int64)
                if last_t is not None and t[0] < last_t:
                    raise EventError(
                        f"{where}: events go back in time: t={t[0]} us follows t={last_t} us of the "
                        f"previous packet; the reader needs the events of a stream in time order"
                    )
                writer.append_events(Events.create(ev["x"], ev["y"], t, ev["on"], self.sensor_size,
                                                   source=where, validate=validate))
                last_t = int(t[-1])
                num_events += len(t)
            elif sid == frame_id and "frame" in packet:
                t_frame = int(packet["frame"]["t"])
                if last_frame_t is not None and t_frame < last_frame_t:
                    raise EventError(f"{where}: frame at t={t_frame} us follows a frame at t={last_frame_t} us")
                writer.add_frame(t_frame, _gray(packet["frame"], self.sensor_size))
                last_frame_t = t_frame

    # everything else is the decoded copy's
    @property
    def t_start(self) -> int:
        return self._inner.t_start

    @property
    def t_end(self) -> int:
        return self._inner.t_end

    def index_at(self, t_us: int) -> int:
        return self._inner.index_at(t_us)

    def events_range(self, i_start: int, i_end: int) -> Events:
        return self._inner.events_range(i_start, i_end)

    def time_of(self, index: int) -> int:
        return self._inner.time_of(index)

    def flow_between(self, t_start: int, t_end: int) -> FlowGT | None:
        return None

    def frame_timestamps(self) -> np.ndarray | None:
        return self._inner.frame_timestamps()

    def frame(self, index: int) -> np.ndarray:
        return self._inner.frame(index)

    def close(self) -> None:
        if self._inner is not None:
            self._inner.close()
            self._inner = None
            self._cache_path.unlink(missing_ok=True)

    def __del__(self) -> None:
        try:
            self.close()
        except Exception:
            pass
