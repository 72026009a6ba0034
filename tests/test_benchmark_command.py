"""scripts/benchmark.py: every section runs end to end at its smallest sizes (``--tiny``), so a
moved file or a changed signature breaks this test rather than a user's benchmark run."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from evflow_cli.commands.benchmark import SECTIONS

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.slow
def test_every_benchmark_section_runs_at_tiny_sizes(tmp_path):
    env = {**os.environ, "OMP_NUM_THREADS": "1"}  # EVFLOW_CACHE: the session cache (conftest.py)
    done = subprocess.run([sys.executable, str(ROOT / "scripts" / "benchmark.py"), "--tiny", "--threads", "1"],
                          capture_output=True, text=True, timeout=900, env=env, cwd=tmp_path)
    assert done.returncode == 0, (done.stdout[-2000:], done.stderr[-4000:])
    rows = [line.split("|") for line in done.stdout.splitlines() if line.count("|") >= 2]
    assert {row[0].strip() for row in rows} == set(SECTIONS)
    torchrun = [row for row in rows if "torchrun 2 process" in row[1]]
    assert torchrun and float(torchrun[0][2].split()[0]) > 0  # the 2-process rows launch scripts/train.py
