#!/usr/bin/env python
"""A copy of a recording (Hagenaars / Monash h5 layout, as devval's) with its events thinned or
repeated, the ground truth and frames untouched: how a network's flow depends on the event density
at a fixed motion (docs/diagnosis-devval.md).

    python tools/resample_events.py ../shared/devval/v260_fast_pan.h5 runs/density/keep0.5.h5 --keep 0.5
    python tools/resample_events.py ../shared/devval/v260_fast_pan.h5 runs/density/x4.h5 --repeat 4
    python tools/error_bins.py --data ../shared/devval/v260_fast_pan.h5 runs/density/*.h5 \\
        --models ev-mgrflownet-cpu-derived-cooldown --dt 1

--keep P keeps each event with probability P (seeded: --seed); --repeat K writes every event K
times at the same pixel and time (more events per active pixel, not more active pixels: not what
a lower contrast threshold would give). The output is written whole, then renamed into place.
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import h5py  # noqa: E402
import numpy as np  # noqa: E402

from envs.atomic import temporary_path  # noqa: E402

FIELDS = ("xs", "ys", "ts", "ps")


def resample(source: Path, target: Path, keep: float = 1.0, repeat: int = 1, seed: int = 0) -> int:
    """Write ``target``: ``source`` with its events thinned to ``keep`` or repeated ``repeat`` times;
    returns the number of events written."""
    if not 0 < keep <= 1 or repeat < 1:
        raise ValueError(f"keep must be in (0, 1] and repeat >= 1, got keep={keep}, repeat={repeat}")
    with h5py.File(source, "r") as f:
        if "events" not in f or any(name not in f["events"] for name in FIELDS):
            raise ValueError(f"{source}: not a Hagenaars / Monash h5 recording (needs events/xs, ys, ts, ps)")
    target.parent.mkdir(parents=True, exist_ok=True)
    tmp = temporary_path(target)
    shutil.copyfile(source, tmp)
    try:
        with h5py.File(tmp, "r+") as f:
            events = {name: f["events"][name][()] for name in FIELDS}
            n = len(events["ts"])
            chosen = np.random.default_rng(seed).random(n) < keep if keep < 1 else np.ones(n, bool)
            for name, values in events.items():
                del f["events"][name]
                f["events"].create_dataset(name, data=np.repeat(values[chosen], repeat))
            polarity = np.repeat(events["ps"][chosen], repeat).astype(bool)
            written = int(polarity.size)
            for key, value in (("num_events", written), ("num_pos", int(polarity.sum())),
                               ("num_neg", int(written - polarity.sum()))):
                if key in f.attrs:
                    f.attrs[key] = value
        os.replace(tmp, target)
    finally:
        tmp.unlink(missing_ok=True)
    return written


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("source", type=Path)
    p.add_argument("target", type=Path)
    p.add_argument("--keep", type=float, default=1.0, help="keep each event with this probability (default 1)")
    p.add_argument("--repeat", type=int, default=1, help="write each kept event this many times (default 1)")
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args(argv)
    try:
        n = resample(args.source, args.target, args.keep, args.repeat, args.seed)
    except ValueError as err:
        p.error(str(err))
    print(f"wrote {args.target}: {n} events")
    return 0


if __name__ == "__main__":
    sys.exit(main())
