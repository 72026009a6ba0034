"""Benchmark section: synthetic simulator throughput.

    python scripts/bench_simulator.py          # every row
    python scripts/bench_simulator.py --dr     # only synthetic-dr-train generation per size

``run(report, quick)`` is imported by evflow_cli/commands/benchmark.py; ``report(section, row_name, value, unit)``
prints one row. Throughput = seconds of simulated 128x128 events per wall-clock second
(single process), at a slow, a medium and a fast split-like scene (max flow 1, 5, 10 px per
30 Hz frame; 2 occluding objects; camera pan, roll and zoom), also per CPU second (robust to
shared cores), plus events per wall second and sub-steps per simulated second.

Generation of the domain-randomised training split (``run_dr``, also in ``run``): seconds of
events per wall second and per CPU second at each training sensor size, over ``per_size``
scenes drawn from the training ranges at that size (their texture building included: the
whole cost of a sequence), one process.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from dataclasses import dataclass

from agents.options import command_parser, options_from_args
from envs.simulator import SceneConfig, simulate
from envs.simulator.randomize import TRAIN_FACTORS, draw_scene

SECTION = "simulator"


def run(report, quick: bool = False, tiny: bool = False) -> None:
    """Every row; ``tiny``: one 0.1 s scene at 64x64 and one training size (checks the section runs)."""
    duration_s, side = (0.1, 64) if tiny else (1.0, 128)
    for max_flow_px in (5.0,) if tiny else (1.0, 5.0, 10.0):
        config = SceneConfig.random(42, side, side, speed_px_s=30.0 * max_flow_px, num_objects=2)
        start, cpu_start = time.perf_counter(), time.process_time()
        sequence = simulate(config, duration_s)
        wall, cpu = time.perf_counter() - start, time.process_time() - cpu_start
        label = f"{side}x{side}, max {max_flow_px:g} px/frame"
        report(SECTION, f"{label}: throughput", duration_s / wall, "sim s / wall s")
        # CPU time: the same figure, less sensitive to other processes sharing the cores
        report(SECTION, f"{label}: throughput (CPU time)", duration_s / cpu, "sim s / CPU s")
        report(SECTION, f"{label}: events", len(sequence.events) / wall / 1e6, "Mev / wall s")
        report(SECTION, f"{label}: sub-steps", sequence.num_substeps / duration_s, "per sim s")
    run_dr(report, per_size=1 if quick or tiny else 3, sizes=TRAIN_FACTORS.sizes[:1] if tiny else None,
           duration_s=duration_s)


def run_dr(report, per_size: int = 3, sizes=None, duration_s: float = 1.0) -> None:
    """synthetic-dr-train generation speed per sensor size (module docstring)."""
    for height, width in sizes or TRAIN_FACTORS.sizes:
        factors = dataclasses.replace(TRAIN_FACTORS, sizes=((height, width),))
        wall = cpu = events = 0.0
        for k in range(per_size):
            config = draw_scene(50_000_000 + k, factors)
            start, cpu_start = time.perf_counter(), time.process_time()
            sequence = simulate(config, duration_s)
            wall += time.perf_counter() - start
            cpu += time.process_time() - cpu_start
            events += len(sequence.events)
        label = f"dr-train {width}x{height} ({per_size} scenes, {duration_s:g} s each)"
        report(SECTION, f"{label}: generation", per_size * duration_s / wall, "sim s / wall s")
        report(SECTION, f"{label}: generation (CPU time)", per_size * duration_s / cpu, "sim s / CPU s")
        report(SECTION, f"{label}: events", events / (per_size * duration_s) / 1e6, "Mev per sim s")


def _print_row(section: str, row_name: str, value: float, unit: str) -> None:
    print(f"{section:<12} {row_name:<48} {value:>10.3f} {unit}")


@dataclass
class BenchSimulatorOptions:
    """Which rows scripts/bench_simulator.py times."""

    dr: bool = False
    """only synthetic-dr-train generation per sensor size"""


def build_parser() -> argparse.ArgumentParser:
    return command_parser(BenchSimulatorOptions, __doc__)


def main(argv=None) -> int:
    args = options_from_args(BenchSimulatorOptions, build_parser().parse_args(argv))
    if args.dr:  # only the randomised split's rows
        run_dr(_print_row)
    else:
        run(_print_row)
    return 0


if __name__ == "__main__":
    sys.exit(main())
