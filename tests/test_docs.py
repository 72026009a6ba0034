"""The Markdown pages: readable text (UTF-8, no control characters pasted from a terminal) whose
relative links lead to files of the repository."""

import re
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _pages() -> list[Path]:
    try:
        listed = subprocess.run(["git", "ls-files", "*.md"], cwd=ROOT, capture_output=True, text=True, check=True)
        names = listed.stdout.split()
    except (OSError, subprocess.CalledProcessError):  # not a git checkout (an sdist): the files on disk
        names = [str(p.relative_to(ROOT)) for p in ROOT.rglob("*.md") if ".venv" not in p.parts]
    return [ROOT / name for name in names if (ROOT / name).is_file()]


PAGES = _pages()
LINK = re.compile(r"\]\(([^)\s]+)\)")


@pytest.mark.parametrize("page", PAGES, ids=[str(p.relative_to(ROOT)) for p in PAGES])
def test_page_is_clean_text_with_working_links(page):
    text = page.read_bytes().decode("utf-8")  # raises on anything but UTF-8
    bad = [(n + 1, repr(ch)) for n, line in enumerate(text.splitlines()) for ch in line
           if ord(ch) < 32 and ch != "\t"]
    assert not bad, f"{page.relative_to(ROOT)}: control characters at lines {bad[:5]}"
    broken = []
    for target in LINK.findall(text):
        if re.match(r"^[a-z]+:", target) or target.startswith("#"):
            continue  # a web address or an anchor of the page
        path = target.split("#", 1)[0]
        if path and not (page.parent / path).exists():
            broken.append(target)
    assert not broken, f"{page.relative_to(ROOT)}: links to missing files: {broken}"


def test_the_readmes_python_blocks_run_as_printed(tmp_path):
    """The README's Python blocks, in order and in one namespace, from a fresh interpreter in the
    checkout's root (the environment, the plug-in model, events from memory); the last reads
    ``events.npy``, which this test writes as convert.py would (a 640 x 480 recording)."""
    import json
    import sys

    import numpy as np

    blocks = re.findall(r"```python\n(.*?)```", (ROOT / "README.md").read_text(), re.S)
    assert len(blocks) >= 3
    n = 200_000
    rng = np.random.default_rng(0)
    events = np.zeros(n, dtype=[("x", "<u2"), ("y", "<u2"), ("t", "<i8"), ("p", "i1")])
    events["x"], events["y"] = rng.integers(0, 640, n), rng.integers(0, 480, n)
    events["t"], events["p"] = np.sort(rng.integers(0, 70_000, n)), rng.integers(0, 2, n)
    np.save(tmp_path / "events.npy", events)
    code = f"""
import os, sys
sys.path.insert(0, {str(ROOT)!r})
os.chdir({str(ROOT)!r})
blocks = {json.dumps(blocks)}
namespace = {{}}
for i, block in enumerate(blocks):
    if "events.npy" in block:
        os.chdir({str(tmp_path)!r})
    exec(compile(block, f"README.md python block {{i + 1}}", "exec"), namespace)
print("flows", namespace["flows"].shape, "bounds", namespace["bounds"].shape)
"""
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    assert "flows (3, 2, 480, 640) bounds (3, 2)" in done.stdout  # 70 ms in 33 ms windows, the last one cut
