"""The code's shape, kept from creeping back: few functions over 60 lines (outside tests/), and
the default window lengths declared once (envs.windows) and read everywhere else."""

from __future__ import annotations

import ast
import inspect
import os
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
#: folders whose code is not counted: environments, run outputs, build outputs, the tests
SKIPPED = {".venv", "runs", "build", "tests"}
MAX_LINES = 60
#: at most this many functions longer than MAX_LINES (counting signature and docstring): the
#: compiled kernel factories and a few functions whose length is their signature and docstring
#: or whose order of random draws / float operations must stay as it is
MAX_LONG_FUNCTIONS = 12


def _long_functions() -> list[tuple[int, str, str]]:
    found = []
    for folder, dirs, files in os.walk(ROOT):
        dirs[:] = [d for d in dirs if d not in SKIPPED]
        for name in files:
            if not name.endswith(".py"):
                continue
            path = Path(folder) / name
            for node in ast.walk(ast.parse(path.read_text())):
                if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                    lines = node.end_lineno - node.lineno + 1
                    if lines > MAX_LINES:
                        found.append((lines, str(path.relative_to(ROOT)), node.name))
    return sorted(found, reverse=True)


def test_few_long_functions():
    found = _long_functions()
    listed = "\n".join(f"  {lines} {path} {name}" for lines, path, name in found)
    assert len(found) <= MAX_LONG_FUNCTIONS, (
        f"{len(found)} functions over {MAX_LINES} lines (at most {MAX_LONG_FUNCTIONS}); split one into "
        f"helpers:\n{listed}")


def test_window_lengths_declared_once():
    from agents import cmax, inference, pretrained
    from envs import env, windows
    from evflow_cli import predict
    from evflow_cli.commands import predict as predict_command

    assert windows.FALLBACK_INTERVAL_US == 33_333
    assert windows.DEFAULT_WINDOW_SIZES == {"frames": 1, "time": 10_000, "count": 15_000}
    assert cmax.FRAME_US == windows.FALLBACK_INTERVAL_US
    assert env.DEFAULT_WINDOW_SIZES is windows.DEFAULT_WINDOW_SIZES
    for function, name in ((pretrained.default_steps, "frame_us"), (inference.predict_flow, "window_us"),
                           (predict.predict, "no_gt_window_us")):
        assert inspect.signature(function).parameters[name].default == windows.FALLBACK_INTERVAL_US, function
    assert predict_command.build_parser().get_default("no_gt_window") == windows.FALLBACK_INTERVAL_US
    assert inspect.signature(windows.iter_windows).parameters["size"].default == windows.DEFAULT_WINDOW_SIZES["time"]
    # hubconf.py imports nothing of the project at load time (torch.hub checks its dependencies
    # first), so its default is a literal: it must match
    hubconf = ast.parse((ROOT / "hubconf.py").read_text())
    flow = next(n for n in hubconf.body if isinstance(n, ast.FunctionDef) and n.name == "flow")
    names = [a.arg for a in flow.args.args]
    defaults = dict(zip(names[len(names) - len(flow.args.defaults):], flow.args.defaults))
    assert ast.literal_eval(defaults["window_us"]) == windows.FALLBACK_INTERVAL_US
