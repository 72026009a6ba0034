"""Open any supported recording: ``open_recording(path, format=None, **options)``.

Formats (``FORMATS``): "evflow-h5" (the project's own, :class:`envs.readers.h5.H5Reader`), "mvsec",
"dsec", "hagenaars", "ecd-text", "aedat4", "prophesee-raw", "prophesee-dat", "numpy" (tonic's
structured x, y, t, p: envs/readers/numpy_events.py). Without ``format`` it is detected from the file:

- a folder: ``events.h5`` (DSEC, also under ``events/left/``), ``events.txt`` (ECD) or a single
  ``*_data.hdf5`` (MVSEC) inside it;
- ``.npy``, or an ``.npz`` holding ``events`` or arrays ``x, y, t, p``: numpy;
- ``.aedat4`` or a file starting with ``#!AER-DAT4``: aedat4;
- ``.raw``, or a ``%`` header naming an EVT format (``% evt``, ``% format EVT``): prophesee-raw;
  ``.dat``, or a ``%`` header saying ``Data file containing``: prophesee-dat;
- an HDF5 file: attribute ``format == "evflow-h5"`` -> evflow-h5; group ``davis`` -> mvsec;
  ``events/xs`` -> hagenaars; ``events/x`` with ``ms_to_idx`` or ``t_offset`` -> dsec;
- any other text file whose first event line holds four numbers: ecd-text.

``options`` go to the reader (e.g. ``crop="center256"`` for MVSEC, ``flow_dir=`` for DSEC).
``sensor_size=(height, width)`` or ``"auto"`` goes to the formats whose files may lack it
(``GEOMETRY_OPTIONAL``: text, Prophesee RAW and DAT; DSEC takes a size, not "auto"); the other
formats store their geometry and keep it (a warning says so when the size given differs), so
one option serves a list of recordings in several formats.
"""

from __future__ import annotations

import os
import warnings
from pathlib import Path

import h5py

from envs.readers.aedat import AedatReader
from envs.readers.base import EventReader, FormatError
from envs.readers.dsec import DSECReader
from envs.readers.h5 import FORMAT_NAME, H5Reader
from envs.readers.hagenaars import HagenaarsReader
from envs.readers.mvsec import MVSECReader
from envs.readers.numpy_events import NumpyEventsReader, is_numpy_events
from envs.readers.prophesee import PropheseeDatReader, PropheseeRawReader
from envs.readers.text import TextReader

__all__ = ["open_recording", "detect_format", "FORMATS", "GEOMETRY_OPTIONAL"]

FORMATS = ("evflow-h5", "mvsec", "dsec", "hagenaars", "ecd-text", "aedat4", "prophesee-raw", "prophesee-dat", "numpy")
_HDF5_MAGIC = b"\x89HDF\r\n\x1a\n"
#: formats whose files may not say their sensor size: their readers take ``sensor_size`` (or "auto")
GEOMETRY_OPTIONAL = ("ecd-text", "prophesee-raw", "prophesee-dat", "numpy")


def _resolve_dir(path: Path) -> tuple[Path, str]:
    for cand, fmt in (
        (path / "events.h5", "dsec"),
        (path / "events" / "left" / "events.h5", "dsec"),
        (path / "events.txt", "ecd-text"),
    ):
        if cand.exists():
            return cand, fmt
    data = sorted(path.glob("*_data.hdf5"))
    if len(data) == 1:
        return data[0], "mvsec"
    raise FormatError(
        f"{path}: a folder without events.h5 (DSEC), events.txt (ECD) or one *_data.hdf5 (MVSEC); "
        "pass the recording file itself"
    )


def _detect_h5(path: Path) -> str:
    try:
        with h5py.File(path, "r") as f:
            if f.attrs.get("format") == FORMAT_NAME:
                return "evflow-h5"
            if "davis" in f:
                return "mvsec"
            if "events" in f and "xs" in f["events"]:
                return "hagenaars"
            if "events" in f and "x" in f["events"] and ("ms_to_idx" in f or "t_offset" in f):
                return "dsec"
            found = sorted(f.keys())
    except OSError as err:
        raise FormatError(f"{path}: not a readable HDF5 file: {err}") from err
    raise FormatError(
        f"{path}: HDF5 file of an unknown layout (top-level entries {found}); expected one of: "
        "attribute format='evflow-h5'; group 'davis' (MVSEC); 'events/xs' (Hagenaars); "
        "'events/x' + 'ms_to_idx' (DSEC)"
    )


def _detect_prophesee(path: Path, head: bytes) -> str | None:
    suffix = path.suffix.lower()
    if suffix == ".raw":
        return "prophesee-raw"
    if suffix == ".dat":
        return "prophesee-dat"
    if head.startswith(b"%"):
        text = head.split(b"\n", 16)
        if any(line.startswith((b"% evt ", b"% format EVT")) for line in text):
            return "prophesee-raw"
        if any(line.startswith(b"% Data file containing") for line in text):
            return "prophesee-dat"
    return None


def detect_format(path: str | os.PathLike) -> tuple[Path, str]:
    """(the file to open, its format name) for a file or folder (module docstring)."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{path}: no such file or folder")
    if path.is_dir():
        return _resolve_dir(path)
    with open(path, "rb") as fh:
        head = fh.read(512)
    if path.suffix.lower() == ".aedat4" or head.startswith(b"#!AER-DAT4"):
        return path, "aedat4"
    prophesee = _detect_prophesee(path, head)
    if prophesee is not None:
        return path, prophesee
    if head.startswith(_HDF5_MAGIC) or path.suffix.lower() in (".h5", ".hdf5"):
        return path, _detect_h5(path)
    if path.suffix.lower() == ".npy" or (path.suffix.lower() == ".npz" and is_numpy_events(path)):
        return path, "numpy"
    if path.suffix.lower() == ".npz":
        raise FormatError(f"{path}: an .npz without events (MVSEC's holds ground truth: open the matching "
                          "*_data.hdf5 instead; events: arrays x, y, t, p or a structured 'events')")
    try:
        lines = head.decode("ascii").splitlines()
    except UnicodeDecodeError:
        lines = []
    for line in lines[:8]:
        tokens = line.split()
        if len(tokens) == 4:
            try:
                [float(v) for v in tokens]
                return path, "ecd-text"
            except ValueError:
                continue
    raise FormatError(f"{path}: cannot tell the format; pass format= one of {FORMATS}")


#: format -> reader class of every format but the project's own (each reader imports its optional
#: extras, aedat or hdf5plugin, only when a file needs them)
_READERS: dict[str, type[EventReader]] = {
    "mvsec": MVSECReader,
    "dsec": DSECReader,
    "hagenaars": HagenaarsReader,
    "ecd-text": TextReader,
    "aedat4": AedatReader,
    "prophesee-raw": PropheseeRawReader,
    "prophesee-dat": PropheseeDatReader,
    "numpy": NumpyEventsReader,
}


def open_recording(path: str | os.PathLike, format: str | None = None, **options) -> EventReader:
    """Open a recording as an :class:`EventReader`; ``format`` one of FORMATS or None (detect)."""
    if format is None:
        path, format = detect_format(path)
    elif Path(path).is_dir():
        resolved, found = _resolve_dir(Path(path))
        path = resolved
    if format != "evflow-h5" and format not in _READERS:
        raise ValueError(f"unknown format {format!r}; expected one of {FORMATS}")
    size = options.pop("sensor_size", None)
    taken = format in GEOMETRY_OPTIONAL or (format == "dsec" and not isinstance(size, str))
    if size is not None and taken:
        options["sensor_size"] = size
    if format == "evflow-h5":
        reader = H5Reader(path, **options)
    else:
        reader = _READERS[format](path, **options)
    if size is not None and not taken and not isinstance(size, str) and tuple(size) != tuple(reader.sensor_size):
        warnings.warn(f"{path}: a {format} file stores its sensor size, {reader.sensor_size[0]}x{reader.sensor_size[1]} "
                      f"(height x width), which it keeps; the sensor size given ({size[0]}x{size[1]}) is for files "
                      f"without one ({', '.join(GEOMETRY_OPTIONAL)})", stacklevel=2)
    return reader
