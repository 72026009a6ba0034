"""Files that appear whole or not at all: ``<name>.tmp-<pid>`` beside the target, renamed over it
when complete.

A write killed before the rename leaves its temporary behind; :func:`remove_stale_temporaries`
deletes those of processes that no longer run, and every writer calls it before it starts, so a
stale temporary never outlives the next run's start.
"""

from __future__ import annotations

import os
from pathlib import Path

__all__ = ["temporary_path", "remove_stale_temporaries", "same_file"]


def temporary_path(path: str | os.PathLike) -> Path:
    """``<path>.tmp-<this pid>``: where a writer puts the file until it is complete."""
    path = Path(path)
    return path.with_name(f"{path.name}.tmp-{os.getpid()}")


def _running(pid: int) -> bool:
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's live process
        return True
    return True


def remove_stale_temporaries(path: str | os.PathLike) -> list[Path]:
    """Delete ``<path>.tmp-<pid>`` files left by processes that are no longer running (a killed
    write); returns the files removed. Temporaries of live processes (a concurrent writer) stay."""
    path = Path(path)
    if not path.parent.is_dir():
        return []
    removed = []
    prefix = f"{path.name}.tmp-"
    for candidate in path.parent.glob(f"{path.name}.tmp-*"):
        pid = candidate.name[len(prefix):]
        if not pid.isdigit() or _running(int(pid)) or not candidate.is_file():
            continue
        candidate.unlink(missing_ok=True)
        removed.append(candidate)
    return removed


def same_file(a: str | os.PathLike, b: str | os.PathLike) -> bool:
    """True when ``a`` and ``b`` are one file on disk: the same path after resolving symlinks, or
    the same inode (a hard link)."""
    if os.path.realpath(a) == os.path.realpath(b):
        return True
    try:
        return os.path.samefile(a, b)
    except OSError:  # one of them does not exist
        return False
