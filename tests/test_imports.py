"""envs/readers/ imports one way: each of its modules imports first in a fresh interpreter, none
reaches into the simulator (envs.synthetic, envs.simulator), and none hides a cycle behind an
import inside a function or a module ``__getattr__``. Also envs/cache.py (the cache root the
simulated sequences and the Prophesee indexes share), the format's names at one address, and the
library's layers (evflow_cli -> agents -> envs -> losses) importing downwards only, and the
training configuration below the learner and its objectives."""

from __future__ import annotations

import ast
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
READERS = ROOT / "envs" / "readers"
READER_FILES = sorted(READERS.glob("*.py"))
#: what a reader must not import: the simulator and the synthetic benchmark built on it
FORBIDDEN = ("envs.synthetic", "envs.simulator")


def _module_name(path: Path) -> str:
    parts = path.relative_to(ROOT).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _imports(path: Path) -> list[tuple[str, int, bool]]:
    """(imported module, line, at module level) for every import in the file, wherever it sits,
    and every ``importlib.import_module("...")`` / ``__import__("...")`` of a constant name."""
    tree = ast.parse(path.read_text(), str(path))
    top = {id(node) for node in tree.body}
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found += [(alias.name, node.lineno, id(node) in top) for alias in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            found.append((node.module, node.lineno, id(node) in top))
        elif (isinstance(node, ast.Call) and node.args and isinstance(node.args[0], ast.Constant)
              and isinstance(node.args[0].value, str)
              and (getattr(node.func, "attr", None) == "import_module" or getattr(node.func, "id", None) == "__import__")):
            found.append((node.args[0].value, node.lineno, False))
    return found


@pytest.mark.parametrize("path", READER_FILES, ids=lambda p: p.name)
def test_each_reader_module_imports_first_in_a_fresh_interpreter(path):
    """Imported before anything else of ours, so no module of the package leans on another
    having been imported first (a cycle shows as an ImportError on a partial module)."""
    module = _module_name(path)
    env = {**os.environ, "PYTHONPATH": str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", "")}
    done = subprocess.run([sys.executable, "-c", f"import {module}"], cwd=ROOT, env=env,
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, f"import {module} first failed:\n{done.stderr}"


@pytest.mark.parametrize("path", READER_FILES, ids=lambda p: p.name)
def test_no_reader_imports_the_simulator(path):
    bad = [f"line {line}: {name}" for name, line, _ in _imports(path)
           if any(name == f or name.startswith(f + ".") for f in FORBIDDEN)]
    assert not bad, f"{path.relative_to(ROOT)} imports the simulator side ({', '.join(bad)}); readers sit below it"


@pytest.mark.parametrize("path", READER_FILES, ids=lambda p: p.name)
def test_readers_import_our_modules_at_module_level_only(path):
    """An import of ours inside a function is how a cycle hides; only optional third-party
    extras (aedat, hdf5plugin, PIL, tqdm) are imported where a file needs them."""
    late = [f"line {line}: {name}" for name, line, top in _imports(path)
            if not top and (name == "envs" or name.startswith("envs.") or name in ("losses", "agents"))]
    assert not late, f"{path.relative_to(ROOT)} imports modules of ours inside a function: {', '.join(late)}"


def test_the_readers_package_has_no_lazy_attributes():
    tree = ast.parse((READERS / "__init__.py").read_text())
    names = {node.name for node in tree.body if isinstance(node, ast.FunctionDef)}
    assert "__getattr__" not in names


def test_the_format_names_have_one_address():
    """The h5 format's names come from envs.readers (re-exported from envs/readers/h5.py), and
    the earlier addresses of moved modules are gone, not kept as re-exports."""
    import envs.readers
    import envs.readers.base
    import envs.readers.h5
    import envs.synthetic
    from envs.cache import cache_root

    for name in ("H5Reader", "H5Writer", "write_h5"):
        assert getattr(envs.readers.h5, name) is getattr(envs.readers, name)
    assert envs.readers.h5.FormatError is envs.readers.base.FormatError is envs.readers.FormatError
    assert envs.synthetic.cache_root is cache_root
    for gone in ("envs/h5format.py", "agents/mirror.py", "agents/subwindows.py", "agents/commands"):
        assert not (ROOT / gone).exists(), f"{gone} is an earlier address; import from its new place"
    import agents.cmax

    assert not hasattr(agents.cmax, "RefinedPolicy")  # agents.wrappers.refine


#: the library's layers, each importing only those after it (scripts and tools sit above them all)
LAYERS = ("evflow_cli", "agents", "envs", "losses")


@pytest.mark.parametrize("package", LAYERS[1:])
def test_the_library_never_imports_the_application(package):
    """agents/, envs/ and losses/ are the library; evflow_cli/ (commands, campaigns, ablations,
    benchmarks, predict's files) is built on it and never imported by it, and each library layer
    imports only the layers below it."""
    above = LAYERS[: LAYERS.index(package)]
    bad = [f"{path.relative_to(ROOT)}:{line}: {name}" for path in sorted((ROOT / package).rglob("*.py"))
           for name, line, _ in _imports(path) if name.split(".")[0] in above]
    assert not bad, f"{package}/ imports a layer above it: {', '.join(bad)}"


def _agents_imports(path: Path) -> set[str]:
    """The modules of agents/ that an agents/ file imports, relatively or by name, anywhere in it."""
    names = {name for name, _, _ in _imports(path)}
    names |= {f"agents.{node.module}" for node in ast.walk(ast.parse(path.read_text()))
              if isinstance(node, ast.ImportFrom) and node.level == 1 and node.module}
    return {name for name in names if name.startswith("agents.")}


def test_the_training_config_sits_below_the_learner_and_its_objectives():
    """agents/train_config.py (TrainConfig, the presets) imports neither the learner nor the
    objectives, and the objectives do not import the learner: no circle among the three."""
    assert not {"agents.learner", "agents.objectives"} & _agents_imports(ROOT / "agents" / "train_config.py")
    assert "agents.learner" not in _agents_imports(ROOT / "agents" / "objectives.py")
    assert "agents.train_config" in _agents_imports(ROOT / "agents" / "objectives.py")
    import agents.learner
    import agents.train_config

    assert agents.learner.TrainConfig is agents.train_config.TrainConfig  # the earlier address still serves


def test_cache_root_follows_evflow_cache(monkeypatch, tmp_path):
    from envs.cache import cache_root

    monkeypatch.setenv("EVFLOW_CACHE", str(tmp_path))
    assert cache_root() == tmp_path
    for off in ("off", "OFF", "0", "none", "", " "):
        monkeypatch.setenv("EVFLOW_CACHE", off)
        assert cache_root() is None
    monkeypatch.delenv("EVFLOW_CACHE")
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    assert cache_root() == tmp_path / "home" / ".cache" / "evflow"
