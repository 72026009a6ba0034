"""Simulate a named synthetic split (envs.synthetic) into project h5 files, one per sequence.

    python scripts/generate_synthetic.py --split synthetic-train --out data/synthetic-train
    python scripts/generate_synthetic.py --split synthetic-test --out data/synthetic-test --num 2

Each file holds the events, 30 Hz frames and the exact flow between consecutive frames
(see envs/h5format.py); its provenance attribute records the split, the sequence spec, the
full scene config and the simulator version. Existing files are skipped unless --overwrite.
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import asdict
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from tqdm import tqdm  # noqa: E402

from envs.synthetic import SPLITS, list_sequences  # noqa: E402


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        description="Simulate a named synthetic split into project h5 files (events, frames, exact flow).",
        epilog="Splits: " + "; ".join(f"{name} ({len(specs)} sequences)" for name, specs in SPLITS.items()),
    )
    parser.add_argument("--split", required=True, choices=list(SPLITS), help="which split to generate")
    parser.add_argument("--out", required=True, type=Path, help="output folder (created); files are <sequence name>.h5")
    parser.add_argument("--num", type=int, default=None, help="only the first N sequences of the split")
    parser.add_argument("--overwrite", action="store_true", help="re-simulate files that already exist")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    return parser.parse_args(argv)


def main(argv=None) -> list[Path]:
    args = parse_args(argv)
    specs = list_sequences(args.split)[: args.num]
    args.out.mkdir(parents=True, exist_ok=True)
    written = []
    start = time.perf_counter()
    bar = tqdm(specs, desc=args.split, unit="seq", disable=args.no_progress)
    for spec in bar:
        path = args.out / f"{spec.name}.h5"
        bar.set_postfix_str(spec.name)
        if path.exists() and not args.overwrite:
            continue
        sequence = spec.simulate()
        sequence.to_h5(path, name=spec.name, provenance={"split": args.split, "spec": asdict(spec)})
        written.append(path)
    print(f"{args.split}: wrote {len(written)} of {len(specs)} files to {args.out} in {time.perf_counter() - start:.1f} s")
    return written


if __name__ == "__main__":
    main()
