"""Benchmark section for envs/readers/: windows/s and peak memory of every streaming reader.

For each h5 format (the project's evflow-h5, MVSEC, DSEC, Hagenaars) a synthetic recording of
``num_events`` uniformly random events at ``rate`` events/s is written in that format's public
layout (chunked and compressed as the real files are: MVSEC and Hagenaars gzip, DSEC
Blosc/zstd), at the format's sensor size (MVSEC 346x260, DSEC 640x480, the others both). A
fresh child process then opens it through ``open_recording`` and reads it as consecutive 10 ms
windows (``iter_windows(reader, "time", 10_000)``; at most ``max_windows``, spread evenly over
the whole file), and reports:

- windows/s (events decoded, converted and validated into ``Events``);
- peak RSS of the child (VmHWM) and, for comparison, the decompressed size of the event
  columns in the file: streaming keeps the first far below the second.

ECD text is measured the same way on min(num_events, 10^6) events (text is slow to write).
AEDAT4 needs the optional ``aedat`` package and a real file, so it has no synthetic row.

``run(report)`` is called by evflow_cli/commands/benchmark.py; ``report(section, row_name, value, unit)``
prints a row. Standalone: ``python scripts/bench_readers.py [--events N] [--rate EV_PER_S]
[--max-windows W] [--formats ...] [--workdir DIR]``; ``--events 100000000`` is the 10^8-event
memory check (needs a few GB of disk and tens of minutes).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from agents.options import command_parser, option, options_from_args, positive_float, positive_int

SECTION = "readers"
DEFAULT_EVENTS = 10_000_000  # ~1-2 minutes on 2 cores; 10^8 is the full memory check
DEFAULT_RATE = 2_000_000  # events per second, a busy DAVIS / Prophesee scene
WINDOW_US = 10_000
CHUNK = 1 << 20
# (format, sensor (height, width), bytes per event once decompressed)
CASES = [
    ("evflow-h5", (260, 346), 13),
    ("evflow-h5", (480, 640), 13),
    ("mvsec", (260, 346), 32),
    ("hagenaars", (260, 346), 13),
    ("hagenaars", (480, 640), 13),
    ("dsec", (480, 640), 9),
    ("ecd-text", (260, 346), None),
]


def _chunks(num_events: int, rate: float, sensor_size, seed: int = 0):
    """Yield (x, y, t_us, p01) chunks of a sorted random stream, CHUNK events at a time."""
    rng = np.random.default_rng(seed)
    h, w = sensor_size
    span = CHUNK / rate * 1e6
    for k, i0 in enumerate(range(0, num_events, CHUNK)):
        n = min(CHUNK, num_events - i0)
        t = np.sort(rng.integers(int(k * span), int(k * span + span * n / CHUNK) + 1, n))
        yield rng.integers(0, w, n), rng.integers(0, h, n), t.astype(np.int64), rng.integers(0, 2, n)


def write_synthetic(fmt: str, path: Path, num_events: int, sensor_size, rate: float = DEFAULT_RATE) -> Path:
    """Write a synthetic recording in ``fmt``'s public layout, streaming (bounded memory)."""
    import h5py

    from envs.events import Events

    chunks = _chunks(num_events, rate, sensor_size)
    if fmt == "evflow-h5":
        from envs.readers import H5Writer

        with H5Writer(path, sensor_size) as writer:
            for x, y, t, p in chunks:
                writer.append_events(Events.create(x, y, t, p, sensor_size, validate=False))
        return path
    if fmt == "ecd-text":
        with open(path, "w") as fh:
            for x, y, t, p in chunks:
                fh.write("".join(f"{ti / 1e6:.6f} {xi} {yi} {pi}\n" for ti, xi, yi, pi in zip(t.tolist(), x.tolist(), y.tolist(), p.tolist())))
        return path
    gzip = {"compression": "gzip", "compression_opts": 1, "shuffle": True}
    with h5py.File(path, "w") as f:
        if fmt == "mvsec":
            ds = {"": f.create_dataset("davis/left/events", (0, 4), np.float64, maxshape=(None, 4), chunks=(1 << 14, 4), **gzip)}
        elif fmt == "hagenaars":
            ds = {k: f.create_dataset(f"events/{k}", (0,), dt, maxshape=(None,), chunks=(1 << 16,), **gzip)
                  for k, dt in (("xs", np.int16), ("ys", np.int16), ("ts", np.float64), ("ps", np.bool_))}
            f.attrs["sensor_resolution"] = sensor_size
            f.attrs["t0"] = 0.0
        elif fmt == "dsec":
            import hdf5plugin

            blosc = dict(hdf5plugin.Blosc(cname="zstd", clevel=1, shuffle=hdf5plugin.Blosc.SHUFFLE))
            ds = {k: f.create_dataset(f"events/{k}", (0,), dt, maxshape=(None,), chunks=(1 << 16,), **blosc)
                  for k, dt in (("x", np.uint16), ("y", np.uint16), ("t", np.uint32), ("p", np.uint8))}
        else:
            raise ValueError(f"no synthetic writer for {fmt!r}")
        n, ms_index, last_t = 0, [], 0
        for x, y, t, p in chunks:
            m = len(t)
            for d in ds.values():
                d.resize((n + m,) + d.shape[1:])
            if fmt == "mvsec":
                ds[""][n:] = np.stack([x, y, 1.5e9 + t / 1e6, np.where(p > 0, 1.0, -1.0)], axis=1)
            elif fmt == "hagenaars":
                ds["xs"][n:], ds["ys"][n:], ds["ts"][n:], ds["ps"][n:] = x, y, t / 1e6, p > 0
            else:
                ds["x"][n:], ds["y"][n:], ds["t"][n:], ds["p"][n:] = x, y, t, p
                bounds = 1000 * np.arange(len(ms_index), int(t[-1]) // 1000 + 1)
                ms_index.extend((n + np.searchsorted(t, bounds, side="left")).tolist())
            n += m
            last_t = int(t[-1])
        if fmt == "dsec":
            f.create_dataset("ms_to_idx", data=np.asarray(ms_index, np.uint64))
            f.create_dataset("t_offset", data=np.int64(0))
        if fmt == "hagenaars":
            f.attrs["duration"] = last_t / 1e6
    return path


def window_starts(t_start: int, t_end: int, max_windows: int) -> np.ndarray:
    """Starts (us) of the 10 ms windows read: all of them, or at most ``max_windows`` in
    consecutive runs of 10 spread over the whole file."""
    starts = np.arange(t_start, t_end, WINDOW_US)
    if len(starts) > max_windows:
        firsts = np.linspace(0, len(starts) - 10, max(1, max_windows // 10)).astype(np.int64)
        starts = starts[(firsts[:, None] + np.arange(10)).ravel()]
    return starts


def peak_rss_mb() -> float:
    """Peak resident memory of this process in MB: VmHWM (Linux; reset by exec, unlike
    ru_maxrss, which keeps the parent's peak from before the fork), else ru_maxrss."""
    try:
        for line in open("/proc/self/status"):
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024
    except OSError:
        pass
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def _child(fmt: str, path: str, max_windows: int) -> dict:
    """Runs in a fresh process: open, read windows, report speed and peak RSS."""
    from envs.readers import open_recording

    rss_before = peak_rss_mb()
    options = {"sensor_size": (260, 346)} if fmt == "ecd-text" else {}
    t_open = time.perf_counter()
    with open_recording(path, fmt, **options) as reader:
        open_s = time.perf_counter() - t_open
        starts = window_starts(reader.t_start, reader.t_end, max_windows)
        events = 0
        t0 = time.perf_counter()
        for s in starts:
            events += len(reader.events_between(int(s), int(s) + WINDOW_US))
        elapsed = time.perf_counter() - t0
        num_events = reader.num_events
    return {
        "windows": len(starts), "events_read": events, "seconds": elapsed, "open_s": open_s,
        "num_events": num_events, "rss_peak_mb": peak_rss_mb(),
        "rss_import_mb": rss_before,
    }


def run(report, num_events: int = DEFAULT_EVENTS, rate: float = DEFAULT_RATE, max_windows: int = 2000,
        formats=None, workdir: str | None = None) -> dict:
    """Write each synthetic file, measure it in a child process, report rows; returns the results."""
    results = {}
    with tempfile.TemporaryDirectory(dir=workdir, prefix="bench_readers-") as tmp:
        for fmt, sensor_size, bytes_per_event in CASES:
            if formats and fmt not in formats:
                continue
            n = min(num_events, 1_000_000) if fmt == "ecd-text" else num_events
            h, w = sensor_size
            path = Path(tmp) / f"{fmt}-{w}x{h}{'.txt' if fmt == 'ecd-text' else '.h5'}"
            t_write = time.perf_counter()
            write_synthetic(fmt, path, n, sensor_size, rate)
            write_s = time.perf_counter() - t_write
            out = subprocess.run(
                [sys.executable, "-m", "evflow_cli.commands.bench_readers", "--child", fmt, str(path), str(max_windows)],
                capture_output=True, text=True, check=False,
            )
            if out.returncode != 0:
                raise RuntimeError(f"bench child for {fmt} failed:\n{out.stderr}")
            res = json.loads(out.stdout.strip().splitlines()[-1])
            res.update(file_mb=path.stat().st_size / 2**20, write_s=write_s)
            label = f"{fmt} {w}x{h} {n / 1e6:g}M ev"
            report(SECTION, f"{label}: 10 ms windows", res["windows"] / res["seconds"], "windows/s")
            report(SECTION, f"{label}: events", res["events_read"] / res["seconds"] / 1e6, "Mev/s")
            report(SECTION, f"{label}: open", res["open_s"] * 1e3, "ms")
            report(SECTION, f"{label}: peak RSS (after import {res['rss_import_mb']:.0f} MB)", res["rss_peak_mb"], "MB")
            report(SECTION, f"{label}: peak RSS growth while reading", res["rss_peak_mb"] - res["rss_import_mb"], "MB")
            if bytes_per_event:
                res["decompressed_mb"] = n * bytes_per_event / 2**20
                report(SECTION, f"{label}: decompressed event columns", res["decompressed_mb"], "MB")
            report(SECTION, f"{label}: file on disk", res["file_mb"], "MB")
            results[(fmt, sensor_size)] = res
            path.unlink()
    return results


def _print_row(section: str, row_name: str, value: float, unit: str) -> None:
    print(f"{section:8s} {row_name:70s} {value:10.2f} {unit}", flush=True)


@dataclass
class BenchReadersOptions:
    """How big the synthetic files of scripts/bench_readers.py are, and which formats it times."""

    events: int = option(DEFAULT_EVENTS, type=positive_int)
    """events per synthetic file (10^8 for the memory check)"""
    rate: float = option(DEFAULT_RATE, type=positive_float)
    """events per second"""
    max_windows: int = option(2000, type=positive_int)
    """10 ms windows read per file (spread evenly)"""
    formats: list[str] | None = option(None, choices=sorted({case[0] for case in CASES}))
    """only these formats (default: every one)"""
    workdir: str | None = None
    """where the synthetic files go (default: system temp)"""


def build_parser() -> argparse.ArgumentParser:
    return command_parser(BenchReadersOptions, __doc__)


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv and argv[0] == "--child":
        print(json.dumps(_child(argv[1], argv[2], int(argv[3]))))
        return 0
    args = options_from_args(BenchReadersOptions, build_parser().parse_args(argv))
    run(_print_row, num_events=args.events, rate=args.rate, max_windows=args.max_windows,
        formats=args.formats, workdir=args.workdir)
    return 0


if __name__ == "__main__":
    sys.exit(main())
