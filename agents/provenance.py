"""What made a run or an export: the package's version and the checkout's git commit (with a
mark when it held uncommitted changes), recorded beside every run's config and every export."""

from __future__ import annotations

import subprocess
from pathlib import Path

__all__ = ["code_version"]

ROOT = Path(__file__).resolve().parents[1]


def code_version() -> dict[str, str | None]:
    """{"package": the installed evflow-gym version (None from a bare checkout), "git_commit": the
    checkout's HEAD (None outside a git checkout), "git_dirty": "yes" when files differ from it}."""
    try:
        from importlib.metadata import PackageNotFoundError, version

        package = version("evflow-gym")
    except PackageNotFoundError:
        package = None
    commit = dirty = None
    try:
        commit = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "HEAD"], capture_output=True, text=True,
                                timeout=10, check=True).stdout.strip() or None
        status = subprocess.run(["git", "-C", str(ROOT), "status", "--porcelain", "--untracked-files=no"],
                                capture_output=True, text=True, timeout=10, check=True).stdout
        dirty = "yes" if status.strip() else "no"
    except (OSError, subprocess.SubprocessError):
        pass
    return {"package": package, "git_commit": commit, "git_dirty": dirty}
