"""A small writer of the AEDAT 4.0 container (iniVation DV software), for test fixtures.

What it writes follows the published AEDAT 4.0 layout; all integers are little-endian:

    "#!AER-DAT4.0\\r\\n"
    u32 size, then an ``IOHeader`` flatbuffer of that size: compression (enum: 0 none, 1 LZ4,
        2 LZ4 high, 3 Zstd, 4 Zstd high), dataTablePosition (i64 byte offset of the file data
        table, -1 when there is none) and infoNode, an XML description (``<dv>`` /
        ``outInfo`` / one node per stream, named by the stream id, with ``typeIdentifier`` and,
        for events and frames, ``info/sizeX``, ``info/sizeY``)
    packets, each: i32 stream id, i32 size, then ``size`` bytes: a size-prefixed flatbuffer
        (file identifier EVTS, FRME or IMUS), compressed as a whole with the file's compression
    the file data table (FTAB: byte offset, header, element count and time span of every
        packet), a size-prefixed flatbuffer compressed like the packets, at dataTablePosition

The flatbuffers are laid out front to back (vtable, table, then what the table points to);
readers only follow offsets, so this is as valid as the back-to-front layout of the official
builders, and every scalar, vector and struct sits at its natural alignment.
"""

from __future__ import annotations

import os
import struct
import xml.etree.ElementTree as ElementTree
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterable, Literal

import numpy as np

__all__ = ["COMPRESSIONS", "MAGIC", "Packet", "Stream", "event_packet", "frame_packet", "imu_packet", "write_aedat4"]

MAGIC = b"#!AER-DAT4.0\r\n"
Compression = Literal["none", "lz4", "lz4-high", "zstd", "zstd-high"]
COMPRESSIONS: dict[str, int] = {"none": 0, "lz4": 1, "lz4-high": 2, "zstd": 3, "zstd-high": 4}
FrameFormat = Literal["gray", "gray16", "bgr", "bgra"]
# The Frame table's format field holds OpenCV matrix type codes (CV_8UC1 = 0, CV_16UC1 = 2...).
_FRAME_FORMATS: dict[str, tuple[int, int, np.dtype]] = {
    "gray": (0, 1, np.dtype(np.uint8)),
    "gray16": (2, 1, np.dtype("<u2")),
    "bgr": (16, 3, np.dtype(np.uint8)),
    "bgra": (24, 4, np.dtype(np.uint8)),
}
# struct Event { t: int64; x: int16; y: int16; on: bool; } padded to 16 bytes, aligned to 8
_EVENT = np.dtype({"names": ["t", "x", "y", "on"], "formats": ["<i8", "<i2", "<i2", "?"],
                   "offsets": [0, 8, 10, 12], "itemsize": 16})


# ------------------------------------------------------------------------------------ flatbuffers
class _Scalar:
    """A table field stored inline: ``fmt`` is a little-endian struct code ("<q", "<h"...; two
    codes for an inline struct of two members), aligned to its size."""

    def __init__(self, fmt: str, *values) -> None:
        self.fmt, self.values, self.size = fmt, values, struct.calcsize(fmt)


class _Ref:
    """A table field holding an offset to something written after the table (``write`` returns
    that thing's position in the buffer)."""

    size = 4

    def __init__(self, write: Callable[[bytearray], int]) -> None:
        self.write = write


Field = _Scalar | _Ref | None  # a table is a list of fields, one per schema slot, None = absent


def _pad(buf: bytearray, align: int, ahead: int = 0) -> None:
    """Zero bytes until ``len(buf) + ahead`` is a multiple of ``align``."""
    buf.extend(b"\0" * (-(len(buf) + ahead) % align))


def _write_table(buf: bytearray, fields: list[Field]) -> int:
    """Append a vtable and its table; return the table's position."""
    present = [(slot, f) for slot, f in enumerate(fields) if f is not None]
    layout, size = {}, 4  # the table starts with its i32 offset to the vtable
    for slot, f in sorted(present, key=lambda item: -item[1].size):  # largest first: no holes
        size += -size % f.size
        layout[slot] = size
        size += f.size
    _pad(buf, 2)
    vtable = len(buf)
    buf.extend(struct.pack(f"<{2 + len(fields)}H", 4 + 2 * len(fields), size,
                           *(layout.get(slot, 0) for slot in range(len(fields)))))
    _pad(buf, max([4] + [f.size for _, f in present]))
    table = len(buf)
    inline = bytearray(size)
    struct.pack_into("<i", inline, 0, table - vtable)  # the vtable sits at table - this
    for slot, f in present:
        if isinstance(f, _Scalar):
            struct.pack_into(f.fmt, inline, layout[slot], *f.values)
    buf.extend(inline)
    for slot, f in present:
        if isinstance(f, _Ref):
            at = table + layout[slot]
            struct.pack_into("<I", buf, at, f.write(buf) - at)  # offsets point forward
    return table


def _struct_vector(elements: np.ndarray) -> _Ref:
    """A vector of structs aligned to 8 (``elements``: a structured array in the struct's layout)."""
    data, count = elements.tobytes(), len(elements)

    def write(buf: bytearray) -> int:
        _pad(buf, 8, ahead=4)  # the structs follow the u32 length
        at = len(buf)
        buf.extend(struct.pack("<I", count))
        buf.extend(data)
        return at

    return _Ref(write)


def _ubyte_vector(data: bytes) -> _Ref:
    def write(buf: bytearray) -> int:
        _pad(buf, 4)
        at = len(buf)
        buf.extend(struct.pack("<I", len(data)))
        buf.extend(data)
        return at

    return _Ref(write)


def _string(text: str) -> _Ref:
    data = text.encode("utf-8")

    def write(buf: bytearray) -> int:
        _pad(buf, 4)
        at = len(buf)
        buf.extend(struct.pack("<I", len(data)))
        buf.extend(data + b"\0")
        return at

    return _Ref(write)


def _table_vector(tables: list[list[Field]]) -> _Ref:
    def write(buf: bytearray) -> int:
        _pad(buf, 4)
        at = len(buf)
        buf.extend(struct.pack(f"<I{len(tables)}I", len(tables), *([0] * len(tables))))
        for k, fields in enumerate(tables):
            slot = at + 4 + 4 * k
            struct.pack_into("<I", buf, slot, _write_table(buf, fields) - slot)
        return at

    return _Ref(write)


def _finish(fields: list[Field], identifier: bytes, *, size_prefixed: bool) -> bytes:
    """A whole flatbuffer: [u32 size of the rest], u32 offset to the root table, identifier."""
    start = 4 if size_prefixed else 0
    buf = bytearray(start + 4) + identifier
    root = _write_table(buf, fields)
    struct.pack_into("<I", buf, start, root - start)
    _pad(buf, 8)
    if size_prefixed:
        struct.pack_into("<I", buf, 0, len(buf) - 4)
    return bytes(buf)


# ---------------------------------------------------------------------------------------- packets
@dataclass(frozen=True)
class Packet:
    """One packet's flatbuffer (size-prefixed, uncompressed) and what the data table says of it:
    element count and first / last timestamp (µs)."""

    flatbuffer: bytes
    num_elements: int
    t_first: int
    t_last: int


def event_packet(t: np.ndarray, x: np.ndarray, y: np.ndarray, on: np.ndarray) -> Packet:
    """An EventPacket (EVTS). t: (N,) int64 µs; x, y: (N,) int16 pixels; on: (N,) bool
    polarity. Written in the given order (nothing is sorted here)."""
    events = np.zeros(len(t), _EVENT)
    events["t"], events["x"], events["y"], events["on"] = t, x, y, on
    flatbuffer = _finish([_struct_vector(events)], b"EVTS", size_prefixed=True)
    return Packet(flatbuffer, len(t), int(t[0]) if len(t) else 0, int(t[-1]) if len(t) else 0)


def frame_packet(
    t: int,
    pixels: np.ndarray,
    *,
    format: FrameFormat = "gray",
    offset: tuple[int, int] = (0, 0),
    exposure_us: int = 1000,
) -> Packet:
    """A Frame (FRME). t: µs; pixels: (H, W) for gray / gray16, (H, W, 3|4) B, G, R[, A]
    order for bgr / bgra; offset: (x, y) of the top-left pixel on the sensor. The frame's
    begin/end and exposure times are t - exposure_us .. t."""
    if format not in _FRAME_FORMATS:
        raise ValueError(f"format must be one of {sorted(_FRAME_FORMATS)}, got {format!r}")
    code, channels, dtype = _FRAME_FORMATS[format]
    pixels = np.asarray(pixels)
    height, width = pixels.shape[:2]
    if pixels.shape != ((height, width) if channels == 1 else (height, width, channels)):
        raise ValueError(f"{format} pixels must have {channels} channel(s), got shape {pixels.shape}")
    begin = t - exposure_us
    fields: list[Field] = [
        _Scalar("<q", t), _Scalar("<q", begin), _Scalar("<q", t), _Scalar("<q", begin), _Scalar("<q", t),
        _Scalar("<b", code), _Scalar("<h", width), _Scalar("<h", height),
        _Scalar("<h", offset[0]), _Scalar("<h", offset[1]),
        _ubyte_vector(pixels.astype(dtype).tobytes()),
    ]
    return Packet(_finish(fields, b"FRME", size_prefixed=True), 1, t, t)


def imu_packet(
    t: np.ndarray,
    accelerometer: np.ndarray,
    gyroscope: np.ndarray,
    temperature: np.ndarray | None = None,
    magnetometer: np.ndarray | None = None,
) -> Packet:
    """An ImuPacket (IMUS). t: (N,) int64 µs; accelerometer: (N, 3) float32 g; gyroscope:
    (N, 3) float32 °/s; temperature: (N,) float32 °C; magnetometer: (N, 3) float32 µT."""
    n = len(t)
    temperature = np.zeros(n, np.float32) if temperature is None else temperature
    magnetometer = np.zeros((n, 3), np.float32) if magnetometer is None else magnetometer
    samples = [
        [_Scalar("<q", int(t[k])), _Scalar("<f", float(temperature[k]))]
        + [_Scalar("<f", float(v)) for v in (*accelerometer[k], *gyroscope[k], *magnetometer[k])]
        for k in range(n)
    ]
    return Packet(_finish([_table_vector(samples)], b"IMUS", size_prefixed=True), n,
                  int(t[0]) if n else 0, int(t[-1]) if n else 0)


# ------------------------------------------------------------------------------------ the file
@dataclass(frozen=True)
class Stream:
    """One output stream of the description. type_identifier: EVTS (polarity events), FRME
    (frames) or IMUS; width / height: the sensor, for EVTS and FRME."""

    type_identifier: Literal["EVTS", "FRME", "IMUS"]
    width: int = 0
    height: int = 0
    source: str = "DAVIS346_00000000"


_DESCRIPTIONS = {"EVTS": ("events", "Array of events (polarity ON/OFF)."),
                 "FRME": ("frames", "Standard frame (8-bit image)."),
                 "IMUS": ("imu", "Inertial Measurement Unit data samples.")}


def _description(streams: dict[int, Stream], compression: str) -> str:
    """The infoNode XML: what DV's recorder writes, reduced to the attributes readers use."""
    dv = ElementTree.Element("dv", version="2.0")
    out_info = ElementTree.SubElement(dv, "node", name="outInfo", path="/mainloop/Recorder/outInfo/")

    def attr(parent, key, kind, value):
        ElementTree.SubElement(parent, "attr", key=key, type=kind).text = str(value)

    for stream_id, stream in sorted(streams.items()):
        path = f"/mainloop/Recorder/outInfo/{stream_id}/"
        node = ElementTree.SubElement(out_info, "node", name=str(stream_id), path=path)
        output_name, description = _DESCRIPTIONS[stream.type_identifier]
        attr(node, "compression", "string", compression.upper().replace("-", "_"))
        attr(node, "originalModuleName", "string", "capture")
        attr(node, "originalOutputName", "string", output_name)
        attr(node, "typeDescription", "string", description)
        attr(node, "typeIdentifier", "string", stream.type_identifier)
        if stream.type_identifier in ("EVTS", "FRME"):
            info = ElementTree.SubElement(node, "node", name="info", path=path + "info/")
            attr(info, "sizeX", "int", stream.width)
            attr(info, "sizeY", "int", stream.height)
            attr(info, "source", "string", stream.source)
    return '<?xml version="1.0" encoding="UTF-8"?>\n' + ElementTree.tostring(dv, encoding="unicode")


def _compress(data: bytes, compression: str) -> bytes:
    if compression == "none":
        return data
    if compression in ("lz4", "lz4-high"):
        import lz4.frame  # the test extra

        level = lz4.frame.COMPRESSIONLEVEL_MINHC if compression == "lz4-high" else 0
        return lz4.frame.compress(data, compression_level=level)
    import zstandard  # the test extra

    return zstandard.ZstdCompressor(level=3 if compression == "zstd" else 19).compress(data)


def _io_header(compression: str, data_table_position: int, description: str) -> bytes:
    # Every field written, defaults included, so the header's size does not depend on them.
    # The decoder reads the u32 size, then parses what follows as a flatbuffer on its own: the
    # alignment counts from there.
    fields: list[Field] = [_Scalar("<i", COMPRESSIONS[compression]), _Scalar("<q", data_table_position),
                           _string(description)]
    flatbuffer = _finish(fields, b"IOHE", size_prefixed=False)
    return struct.pack("<I", len(flatbuffer)) + flatbuffer


def _data_table(entries: list[tuple[int, int, int, Packet]]) -> bytes:
    """FileDataTable (FTAB): per packet its byte offset, PacketHeader struct (stream id, size),
    element count and time span."""
    definitions = [
        [_Scalar("<q", offset), _Scalar("<ii", stream_id, size), _Scalar("<q", p.num_elements),
         _Scalar("<q", p.t_first), _Scalar("<q", p.t_last)]
        for offset, stream_id, size, p in entries
    ]
    return _finish([_table_vector(definitions)], b"FTAB", size_prefixed=True)


def write_aedat4(
    path: str | os.PathLike,
    streams: dict[int, Stream],
    packets: Iterable[tuple[int, Packet]],
    *,
    compression: Compression = "none",
    data_table: bool = True,
) -> Path:
    """Write an AEDAT 4.0 file. streams: the description's streams by id; packets: (stream id,
    packet) in file order; data_table: False writes dataTablePosition = -1 and no table, like
    a recording that was interrupted. Returns the path."""
    if compression not in COMPRESSIONS:
        raise ValueError(f"compression must be one of {sorted(COMPRESSIONS)}, got {compression!r}")
    description = _description(streams, compression)
    header_size = len(_io_header(compression, 0, description))
    body = bytearray()
    entries = []
    start = len(MAGIC) + header_size
    for stream_id, packet in packets:
        data = _compress(packet.flatbuffer, compression)
        entries.append((start + len(body), stream_id, len(data), packet))
        body.extend(struct.pack("<ii", stream_id, len(data)) + data)
    position = start + len(body) if data_table else -1
    with open(path, "wb") as f:
        f.write(MAGIC)
        f.write(_io_header(compression, position, description))
        f.write(body)
        if data_table:
            f.write(_compress(_data_table(entries), compression))
    return Path(path)
