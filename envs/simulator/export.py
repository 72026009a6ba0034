"""Writing a :class:`SimulatedSequence` in the recording formats the project reads.

- ``evflow-h5`` (one ``.h5`` file): events, 30 Hz frames and the exact flow between
  consecutive frames (:meth:`SimulatedSequence.to_h5`).
- ``hagenaars`` (one ``.h5`` file, the event_flow / HQF layout of
  :mod:`envs.readers.hagenaars`): ``events/xs, ys, ts (s), ps``, ``images/image<k>`` and
  ``flow_dt1/flow<k>`` with ``timestamp_from`` / ``timestamp`` (start / end of the interval).
  That layout has no valid mask: its reader takes an exactly zero flow vector as invalid, so a
  still camera's background loses its (zero) ground truth there; evflow-h5 keeps it.
- ``ecd-text`` (a folder, as the Event Camera Dataset): ``events.txt`` (a ``width height``
  header, then ``t x y p`` lines, t in seconds, p in {0, 1}), ``images.txt`` and
  ``images/frame_<k>.png``. The text format has no ground truth.

    path = write_sequence(sequence, "out/seq0", "hagenaars", name="seq0")   # -> out/seq0.h5
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Literal, get_args

import numpy as np

from envs.atomic import temporary_path
from envs.simulator.simulate import SIMULATOR_VERSION, SimulatedSequence

__all__ = ["OutputFormat", "OUTPUT_FORMATS", "output_path", "write_sequence"]

OutputFormat = Literal["evflow-h5", "hagenaars", "ecd-text"]
OUTPUT_FORMATS: tuple[str, ...] = get_args(OutputFormat)


def output_path(stem: str | os.PathLike, fmt: OutputFormat) -> Path:
    """The file (``.h5``) or folder (ecd-text) a sequence written as ``fmt`` at ``stem`` gets."""
    _check_format(fmt)
    stem = Path(stem)
    return stem if fmt == "ecd-text" else stem.with_name(stem.name + ".h5")


def write_sequence(
    sequence: SimulatedSequence, stem: str | os.PathLike, fmt: OutputFormat = "evflow-h5", *, name: str = "synthetic",
    provenance: dict | None = None,
) -> Path:
    """Write ``sequence`` as ``fmt`` at :func:`output_path` (stem, fmt); returns that path.
    The file (or folder) appears under its final name only once complete."""
    path = output_path(stem, fmt)
    path.parent.mkdir(parents=True, exist_ok=True)
    if fmt == "evflow-h5":
        return sequence.to_h5(path, name=name, provenance=provenance)
    info = {"simulator_version": SIMULATOR_VERSION, "scene_config": sequence.config.to_dict(), **(provenance or {})}
    tmp = temporary_path(path)  # host and pid: a cache may be shared by several machines
    if fmt == "hagenaars":
        _write_hagenaars(sequence, tmp, info)
    else:
        _write_ecd_text(sequence, tmp, info)
    os.replace(tmp, path)
    return path


def _check_format(fmt: str) -> None:
    if fmt not in OUTPUT_FORMATS:
        raise ValueError(f"output format must be one of {OUTPUT_FORMATS}, got {fmt!r}")


def _write_hagenaars(sequence: SimulatedSequence, path: Path, info: dict) -> None:
    import h5py

    ev = sequence.events
    times = sequence.frame_times
    with h5py.File(path, "w") as f:
        f.attrs["sensor_resolution"] = np.array(sequence.sensor_size, np.int64)
        f.attrs["t0"] = 0.0
        f.attrs["duration"] = sequence.duration_us * 1e-6
        f.attrs["provenance"] = json.dumps(info)
        compress = {"compression": "gzip", "compression_opts": 1}
        f.create_dataset("events/xs", data=ev.x, **compress)
        f.create_dataset("events/ys", data=ev.y, **compress)
        f.create_dataset("events/ts", data=ev.t * 1e-6, **compress)
        f.create_dataset("events/ps", data=ev.p > 0, **compress)
        for k, (t_us, image) in enumerate(zip(times, sequence.frames)):
            f.create_dataset(f"images/image{k:09d}", data=image, **compress).attrs["timestamp"] = t_us * 1e-6
        for k in range(len(times) - 1):
            flow, _ = sequence.flow_between(int(times[k]), int(times[k + 1]))
            d = f.create_dataset(f"flow_dt1/flow{k:09d}", data=flow, **compress)
            d.attrs["timestamp_from"] = times[k] * 1e-6
            d.attrs["timestamp"] = times[k + 1] * 1e-6


def _write_ecd_text(sequence: SimulatedSequence, folder: Path, info: dict) -> None:
    from PIL import Image

    (folder / "images").mkdir(parents=True)
    ev = sequence.events
    h, w = sequence.sensor_size
    # fixed-point seconds with 6 decimals: the microsecond times come back exactly
    seconds, micros = np.divmod(ev.t, 1_000_000)
    lines = np.char.add(np.char.add(seconds.astype(str), "."), np.char.zfill(micros.astype(str), 6))
    columns = [lines, ev.x.astype(str), ev.y.astype(str), (ev.p > 0).astype(np.int8).astype(str)]
    with open(folder / "events.txt", "w") as fh:
        fh.write(f"{w} {h}\n")
        chunk = 1 << 18
        for i in range(0, len(ev), chunk):
            rows = [c[i : i + chunk] for c in columns]
            fh.write("\n".join(" ".join(r) for r in zip(*rows)) + "\n")
    listing = []
    for k, (t_us, image) in enumerate(zip(sequence.frame_times, sequence.frames)):
        Image.fromarray(image).save(folder / "images" / f"frame_{k:08d}.png")
        listing.append(f"{t_us / 1e6:.6f} images/frame_{k:08d}.png")
    (folder / "images.txt").write_text("\n".join(listing) + "\n")
    (folder / "provenance.json").write_text(json.dumps(info))
