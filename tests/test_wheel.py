"""The installed package: a wheel built from this checkout carries the code and the default model
only (<= 10 MB), runs from site-packages (the benchmark included), loads the other shipped
models only from a checkout, and writes nothing into itself (campaigns, exports)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def test_package_data_names_the_default_model():
    """pyproject.toml's package-data lists the files of the model default.json names (a change of
    default that forgets pyproject would ship a wheel without its default)."""
    tomllib = pytest.importorskip("tomllib")  # Python 3.11+
    listed = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["package-data"]["agents"]
    default = json.loads((ROOT / "agents" / "weights" / "default.json").read_text())["model"]
    assert sorted(listed) == sorted(["weights/default.json", f"weights/{default}.pt", f"weights/{default}.json"])


@pytest.fixture(scope="module")
def installed(tmp_path_factory) -> Path:
    """The wheel built from this checkout, unpacked as site-packages would hold it."""
    out = tmp_path_factory.mktemp("wheel")
    done = subprocess.run([sys.executable, "-m", "pip", "wheel", str(ROOT), "--no-deps", "--no-build-isolation", "-q",
                           "-w", str(out)], capture_output=True, text=True, timeout=300, cwd=out)
    if done.returncode != 0:
        pytest.fail(f"pip wheel failed: {done.stderr[-2000:]}")
    (wheel,) = out.glob("*.whl")
    site = out / "site"
    with zipfile.ZipFile(wheel) as z:
        names = z.namelist()
        z.extractall(site)
    assert wheel.stat().st_size <= 10 * 2**20, f"the wheel weighs {wheel.stat().st_size / 2**20:.1f} MB"
    assert not any(n.startswith(("tests/", "agents/campaigns/", "runs/")) for n in names)
    assert sorted(n for n in names if n.endswith(".pt")) == [
        f"agents/weights/{json.loads((ROOT / 'agents/weights/default.json').read_text())['model']}.pt"]
    return site


def _run(site: Path, code: str, cwd: Path, *args: str) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": str(site)}  # ahead of the checkout's editable install
    return subprocess.run([sys.executable, "-c", code, *args], capture_output=True, text=True, timeout=300, cwd=cwd,
                          env=env)


def test_the_installed_package_runs_the_default_and_refuses_what_needs_a_checkout(installed, tmp_path):
    code = """
import json, sys
import numpy as np
import agents, agents.pretrained as shipped
from agents.policy import RecurrentPolicy
from evflow_cli.campaign import Campaign
from envs.recordings import write_translating_recording  # what the benchmark writes its recordings with
out = {"file": agents.__file__, "in_checkout": shipped.IN_CHECKOUT, "models": shipped.list_pretrained()}
policy = RecurrentPolicy.from_pretrained()
out["default"] = type(policy.model).__name__
for name, call in [("other", lambda: RecurrentPolicy.from_pretrained("ev-mgrflownet-cpu-synthetic")),
                   ("campaign", lambda: Campaign("mine")),
                   ("export", lambda: shipped.export_pretrained("x.pt", "mine", {}))]:
    try:
        call()
        out[name] = None
    except (KeyError, ValueError) as err:
        out[name] = str(err)
print(json.dumps(out))
"""
    done = _run(installed, code, tmp_path)
    assert done.returncode == 0, done.stderr[-3000:]
    out = json.loads(done.stdout.strip().splitlines()[-1])
    default = json.loads((ROOT / "agents/weights/default.json").read_text())["model"]
    assert out["file"].startswith(str(installed)) and out["in_checkout"] is False
    assert out["models"] == [default] and out["default"] == "EVMGRFlowNet"
    assert "in this installation" in out["other"] and "checkout" in out["other"]
    assert "installed package" in out["campaign"] and "installed package" in out["export"]
    assert not list(installed.glob("agents/campaigns*")) and not list(tmp_path.iterdir())


def test_the_benchmark_runs_from_the_installed_package(installed, tmp_path):
    done = _run(installed, "import sys; from evflow_cli.commands.cli import benchmark; sys.argv[0] = 'evflow-benchmark'; "
                           "sys.exit(benchmark())", tmp_path, "--tiny", "--only", "readers")
    assert done.returncode == 0, done.stderr[-3000:]
    assert "readers" in done.stdout and "Traceback" not in done.stderr
