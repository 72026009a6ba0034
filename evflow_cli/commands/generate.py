"""Simulate a named synthetic split (envs.synthetic) into files, one per sequence.

    python scripts/generate_synthetic.py --split synthetic-train --out data/synthetic-train
    python scripts/generate_synthetic.py --split synthetic-test --out data/synthetic-test --num 2
    python scripts/generate_synthetic.py --split synthetic-stress --out data/stress --format hagenaars
    python scripts/generate_synthetic.py --split synthetic-dr-train:2000 --cache --workers 2

Formats (--format): evflow-h5 (default: events, 30 Hz frames, exact flow between consecutive
frames; see envs/readers/h5.py), hagenaars (the event_flow / HQF h5 layout, same content, but
its readers take exactly zero flow as invalid: still backgrounds lose their ground truth),
ecd-text (a folder per sequence: events.txt, images.txt, frames; no flow). Every output records
the split, the sequence spec, the full scene config and the simulator version.

--cache fills the disk cache that training reads (envs.synthetic.load_sequence, under
$EVFLOW_CACHE) instead of a folder: run it before training, or beside it in the background,
so that training does not wait on the simulator. Existing files are skipped unless --overwrite.
"""

from __future__ import annotations

import argparse
import textwrap
import time
from dataclasses import dataclass
from pathlib import Path

from agents.options import Progress, command_parser, option, options_from_args, positive_int
from envs.simulator.export import OUTPUT_FORMATS
from envs.synthetic import SERIES, SPLITS, generate_split, list_sequences


def split_name(text: str) -> str:
    """argparse type: a known split, or SERIES:N (e.g. synthetic-dr-train:N)."""
    try:
        list_sequences(text)
    except ValueError as err:
        raise argparse.ArgumentTypeError(str(err)) from None
    return text


@dataclass(kw_only=True)
class GenerateOptions(Progress):
    """Which split scripts/generate_synthetic.py simulates, and where it writes."""

    split: str = option(required=True, type=split_name)
    """which split to generate"""
    out: Path | None = option(None, exclusive="where", required=True)
    """output folder (created); outputs are named after the sequences"""
    cache: bool = option(False, exclusive="where")
    """fill the disk cache that training reads ($EVFLOW_CACHE)"""
    format: str = option("evflow-h5", choices=OUTPUT_FORMATS)
    """output format"""
    num: int | None = option(None, type=positive_int)
    """only the first N sequences of the split"""
    workers: int = option(1, type=positive_int)
    """simulate in this many processes"""
    overwrite: bool = False
    """re-simulate files that already exist"""


def build_parser() -> argparse.ArgumentParser:
    return command_parser(
        GenerateOptions, __doc__,
        epilog=textwrap.fill("Splits: " + "; ".join(f"{name} ({len(specs)} sequences)" for name, specs in SPLITS.items())
                             + "; " + ", ".join(f"{name}:N" for name in SERIES) + " (a series' first N sequences, any N)",
                             width=79, break_on_hyphens=False),
    )


def parse_args(argv=None) -> GenerateOptions:
    return options_from_args(GenerateOptions, build_parser().parse_args(argv))


def main(argv=None) -> int:
    args = parse_args(argv)
    if args.cache and args.format != "evflow-h5":
        raise SystemExit("--cache holds evflow-h5 files only; use --out for other formats")
    start = time.perf_counter()
    written = generate_split(
        args.split, None if args.cache else args.out, fmt=args.format, num=args.num, workers=args.workers,
        overwrite=args.overwrite, progress=not args.no_progress,
    )
    total = len(list_sequences(args.split)[: args.num])
    where = "the disk cache" if args.cache else args.out
    print(f"{args.split}: wrote {len(written)} of {total} sequences to {where} in {time.perf_counter() - start:.1f} s")
    return 0


if __name__ == "__main__":
    main()
