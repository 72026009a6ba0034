"""Convert any reader to the project h5 format (``scripts/convert.py`` is the command line), or
its events alone to ``.npy`` / ``.npz`` (a structured array with fields x, y, t, p: tonic's
layout; envs/readers/numpy_events.py) when the output's name ends so.

Events are copied ``chunk_events`` at a time (memory stays one chunk deep); ground truth is
stored for the windows ``[T_k, T_{k+flow_dt})`` of the reader's ``flow_timestamps()`` grid where
the reader has it (stepping by flow_dt, like the "frames" windows); frames are copied as
(H, W) uint8. The output is written under a temporary name and renamed at the end
(:class:`envs.readers.h5.H5Writer`), so an interrupted conversion leaves no file behind (and a
killed one's temporary is removed by the next conversion to that name).

Refused before anything is written (:class:`envs.outputs.Output`): an existing output unless
``overwrite=True``; an output that is the input file itself (also through a symlink or a hard
link), whatever ``overwrite`` says (an MVSEC file also holds IMU, depth and the other camera); an
output that is a folder or that another process is writing now; a ``chunk_events`` that is not a
positive integer.
Rectified (float) coordinates are rounded to the nearest pixel, since the project h5 stores
integer pixels; events that round outside the sensor are dropped.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from envs.events import Events
from envs.outputs import Output
from envs.readers.base import EventReader
from envs.readers.h5 import H5Writer
from envs.readers.numpy_events import write_numpy_events

__all__ = ["convert_recording"]


def _integer_pixels(events: Events) -> Events:
    if not np.issubdtype(events.x.dtype, np.floating):
        return events
    h, w = events.sensor_size
    x = np.floor(events.x + 0.5).astype(np.int64)
    y = np.floor(events.y + 0.5).astype(np.int64)
    keep = (x >= 0) & (x < w) & (y >= 0) & (y < h)
    return Events(x[keep].astype(np.int16), y[keep].astype(np.int16), events.t[keep], events.p[keep], events.sensor_size)


def _to_uint8(image: np.ndarray) -> np.ndarray:
    image = np.asarray(image)
    if image.dtype == np.uint8:
        return image
    if image.dtype == np.uint16:
        return (image >> 8).astype(np.uint8)
    return np.clip(np.rint(image), 0, 255).astype(np.uint8)


def _copy_recording(reader: EventReader, writer: H5Writer, chunk_events: int, flow_dt: int | None, frames: bool,
                    bar) -> None:
    """Copy ``reader``'s events (``chunk_events`` at a time, counted on ``bar`` if any), its
    ground truth every ``flow_dt`` grid steps (None: none) and its frames (``frames``) to ``writer``."""
    for i0 in range(0, reader.num_events, chunk_events):
        i1 = min(reader.num_events, i0 + chunk_events)
        writer.append_events(_integer_pixels(reader.events_range(i0, i1)))
        if bar is not None:
            bar.update(i1 - i0)
    grid = reader.flow_timestamps() if flow_dt else None
    if grid is not None:
        ts = np.asarray(grid, np.int64)[::flow_dt]
        for t0, t1 in zip(ts[:-1], ts[1:]):
            gt = reader.flow_between(int(t0), int(t1))
            if gt is not None:
                writer.add_flow(int(t0), int(t1), gt[0], gt[1])
    frame_t = reader.frame_timestamps() if frames else None
    if frame_t is not None:
        for k, t in enumerate(np.asarray(frame_t, np.int64)):
            writer.add_frame(int(t), _to_uint8(reader.frame(k)))


def convert_recording(
    reader: EventReader,
    out_path: str | os.PathLike | Output,
    *,
    chunk_events: int = 1 << 20,
    flow_dt: int | None = 1,
    frames: bool = True,
    progress: bool = False,
    source: str | None = None,
    overwrite: bool = False,
) -> Path:
    """Write ``reader`` to ``out_path`` (a path, or an :class:`envs.outputs.Output` claimed before
    the reader was opened) as a project h5 file; returns the path.

    chunk_events: events per read/write step, a positive int.
    flow_dt: grid steps per stored ground-truth map (None: no ground truth).
    progress: show a tqdm bar over the events.
    source: the input the user named (a file or folder), also compared with ``out_path``.
    overwrite: replace an existing ``out_path`` (never the input itself).
    """
    target, out_path = out_path, out_path.path if isinstance(out_path, Output) else Path(out_path)
    if isinstance(chunk_events, bool) or not isinstance(chunk_events, (int, np.integer)) or chunk_events <= 0:
        raise ValueError(f"chunk_events must be a positive integer (events per read/write step), got {chunk_events!r}")
    inputs = [("recording", getattr(reader, "path", None)), ("recording", source)]
    provenance = {"source": source or str(getattr(reader, "path", reader.name)), "reader": type(reader).__name__}
    if getattr(reader, "crop", None) is not None:
        provenance["crop"] = list(reader.crop)
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=reader.num_events, unit="ev", unit_scale=True, desc=f"convert {reader.name}")
    if out_path.suffix.lower() in (".npy", ".npz"):  # events only, tonic's layout (envs/readers/numpy_events.py)
        claim = target if isinstance(target, Output) else Output(out_path, inputs=inputs, overwrite=overwrite)
        try:
            return write_numpy_events(reader, claim, chunk_events, bar)
        except BaseException:
            claim.discard()
            raise
        finally:
            if bar is not None:
                bar.close()
    try:
        with H5Writer(target, reader.sensor_size, name=reader.name, provenance=provenance, t_start_us=reader.t_start,
                      t_end_us=reader.t_end, overwrite=overwrite, inputs=inputs, exclusive=True) as writer:
            _copy_recording(reader, writer, chunk_events, flow_dt, frames, bar)
    finally:
        if bar is not None:
            bar.close()
    return out_path
