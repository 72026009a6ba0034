"""Resolving a ``data`` argument into a list of recordings, opened lazily.

``data`` is one of: a synthetic split name (``"synthetic-train"``, ``"synthetic-test"``,
``"synthetic-mini"``, ...), a path to a recording in any supported format, a directory
(every recording file inside it, sorted by name), events held in memory (a structured array with
fields x, y, t, p, a mapping of those arrays, or ``Events``: envs/memory.py, with
``options["sensor_size"]``), or a list mixing these. Each recording is
opened only when an episode first needs it, and kept open afterwards.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Sequence

from envs.memory import dataset_sample_events, events_from_memory, is_event_data, is_event_dataset, sensor_size_of
from envs.readers.base import ArrayReader, EventReader

__all__ = ["SequenceSource", "resolve_data", "RECORDING_SUFFIXES"]

RECORDING_SUFFIXES = (".h5", ".hdf5", ".txt", ".aedat4", ".raw", ".dat", ".npy")


@dataclass
class SequenceSource:
    """One recording: its name, how to open it, and its (height, width) when known without
    opening it (synthetic splits)."""

    name: str
    open: Callable[[], EventReader]
    sensor_size: tuple[int, int] | None = None
    _reader: EventReader | None = field(default=None, repr=False)

    def reader(self) -> EventReader:
        if self._reader is None:
            self._reader = self.open()
        return self._reader

    def close(self) -> None:
        if self._reader is not None:
            self._reader.close()
            self._reader = None


def _open_path(path: Path, fmt: str | None, options: dict) -> EventReader:
    from envs.readers import open_recording

    return open_recording(path, format=fmt, **options)


def _synthetic_sources(split: str) -> list[SequenceSource]:
    from envs import synthetic

    specs = synthetic.list_sequences(split)
    return [
        SequenceSource(spec.name, (lambda i=i: synthetic.load_sequence(split, i)), (spec.height, spec.width))
        for i, spec in enumerate(specs)
    ]


def _dataset_sources(dataset, options: dict) -> list[SequenceSource]:
    """A tonic-style dataset's samples as recordings named ``<class>-<index>``, each opened when
    first read, at the dataset's ``sensor_size`` (tonic's (width, height, polarities)) unless the
    options give one."""
    kind = type(dataset).__name__
    size = sensor_size_of(options.get("sensor_size") or dataset.sensor_size, source=f"data {kind}")
    if len(dataset) == 0:
        raise ValueError(f"data: the dataset {kind} holds no samples")

    def opener(index: int):
        name = f"{kind}-{index}"
        events = events_from_memory(dataset_sample_events(dataset, index), size, source=f"data {name}")
        return ArrayReader(events, name=name)

    return [SequenceSource(f"{kind}-{i}", (lambda i=i: opener(i)), size if isinstance(size, tuple) else None)
            for i in range(len(dataset))]


def _is_synthetic_name(item) -> bool:
    return isinstance(item, str) and item.startswith("synthetic") and not os.path.exists(item)


def resolve_data(
    data: str | os.PathLike | Sequence, *, format: str | None = None, options: dict | None = None
) -> list[SequenceSource]:
    """Turn ``data`` into recordings. ``format`` and ``options`` (reader keyword arguments,
    e.g. ``{"crop": "center256"}`` for MVSEC) go to ``envs.readers.open_recording``.
    Raises FileNotFoundError naming a missing path and ValueError for an unknown split or an
    empty directory."""
    options = dict(options or {})
    if is_event_dataset(data):  # tonic's datasets: one recording per sample, opened when first read
        return _dataset_sources(data, options)
    items = [data] if isinstance(data, (str, os.PathLike)) or is_event_data(data) else list(data)
    if not items:
        raise ValueError("data: empty list of recordings")
    sources: list[SequenceSource] = []
    for index, item in enumerate(items):
        if is_event_data(item):  # events held in memory (envs/memory.py): sensor_size from the options
            name = "events" if len(items) == 1 else f"events-{index}"
            events = events_from_memory(item, options.get("sensor_size"), source=f"data {name}")
            sources.append(SequenceSource(name, (lambda e=events, n=name: ArrayReader(e, name=n)), events.sensor_size))
            continue
        if _is_synthetic_name(item):
            sources.extend(_synthetic_sources(str(item)))
            continue
        path = Path(item)
        if not path.exists():
            raise FileNotFoundError(
                f"data: {path} does not exist (expected a recording file, a directory of "
                f"recordings, or a synthetic split name such as 'synthetic-train')"
            )
        if path.is_dir():
            files = sorted(p for p in path.iterdir() if p.suffix.lower() in RECORDING_SUFFIXES)
            if not files:
                raise ValueError(f"data: directory {path} holds no recordings ({', '.join(RECORDING_SUFFIXES)})")
        else:
            files = [path]
        for f in files:
            sources.append(SequenceSource(f.stem, (lambda f=f: _open_path(f, format, options))))
    return sources
