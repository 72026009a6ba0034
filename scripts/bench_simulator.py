"""Benchmark section: synthetic simulator throughput.

    python scripts/bench_simulator.py

``run(report)`` is imported by scripts/benchmark.py; ``report(section, row_name, value, unit)``
prints one row. Throughput = seconds of simulated 128x128 events per wall-clock second
(single process), at a slow, a medium and a fast split-like scene (max flow 1, 5, 10 px per
30 Hz frame; 2 occluding objects; camera pan, roll and zoom), also per CPU second (robust to
shared cores), plus events per wall second and sub-steps per simulated second.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from envs.simulator import SceneConfig, simulate  # noqa: E402

SECTION = "simulator"


def run(report) -> None:
    duration_s = 1.0
    for max_flow_px in (1.0, 5.0, 10.0):
        config = SceneConfig.random(42, 128, 128, speed_px_s=30.0 * max_flow_px, num_objects=2)
        start, cpu_start = time.perf_counter(), time.process_time()
        sequence = simulate(config, duration_s)
        wall, cpu = time.perf_counter() - start, time.process_time() - cpu_start
        label = f"128x128, max {max_flow_px:g} px/frame"
        report(SECTION, f"{label}: throughput", duration_s / wall, "sim s / wall s")
        # CPU time: the same figure, less sensitive to other processes sharing the cores
        report(SECTION, f"{label}: throughput (CPU time)", duration_s / cpu, "sim s / CPU s")
        report(SECTION, f"{label}: events", len(sequence.events) / wall / 1e6, "Mev / wall s")
        report(SECTION, f"{label}: sub-steps", sequence.num_substeps / duration_s, "per sim s")


def _print_row(section: str, row_name: str, value: float, unit: str) -> None:
    print(f"{section:<12} {row_name:<48} {value:>10.3f} {unit}")


if __name__ == "__main__":
    run(_print_row)
