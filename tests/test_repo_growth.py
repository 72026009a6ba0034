"""tools/repo_growth.py: what a round adds to the repository, against a repository made here."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from tools.repo_growth import added_objects  # noqa: E402


def _git(root: Path, *args: str) -> str:
    env = {**os.environ, "GIT_AUTHOR_NAME": "t", "GIT_AUTHOR_EMAIL": "t@t", "GIT_COMMITTER_NAME": "t",
           "GIT_COMMITTER_EMAIL": "t@t"}
    return subprocess.run(["git", *args], cwd=root, check=True, capture_output=True, text=True, env=env).stdout


def test_growth_counts_what_was_added_since_the_base_and_nothing_before(tmp_path):
    try:
        _git(tmp_path, "init", "-q")
    except (OSError, subprocess.CalledProcessError):
        pytest.skip("no git")
    (tmp_path / "old.bin").write_bytes(os.urandom(50_000))
    _git(tmp_path, "add", "old.bin")
    _git(tmp_path, "commit", "-q", "-m", "base")
    base = _git(tmp_path, "rev-parse", "HEAD").strip()
    (tmp_path / "new.bin").write_bytes(os.urandom(200_000))  # incompressible: stored at about its size
    (tmp_path / "small.txt").write_text("a line\n" * 1000)  # compresses to little
    _git(tmp_path, "add", ".")
    _git(tmp_path, "commit", "-q", "-m", "round")
    rows = added_objects(base, root=tmp_path)
    paths = [path for _, _, path in rows]
    assert paths[0] == "new.bin" and "old.bin" not in paths and "small.txt" in paths
    assert 200_000 <= rows[0][0] <= 201_000
    assert sum(size for size, _, _ in rows) < 202_000  # the text, the tree and the commit are small
    assert sum(size for size, _, _ in added_objects(None, root=tmp_path)) >= 250_000  # everything
