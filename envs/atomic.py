"""Files that appear whole or not at all: ``<name>.tmp-<host>-<pid>`` beside the target, renamed
over it when complete.

A write killed before the rename leaves its temporary behind; :func:`remove_stale_temporaries`
deletes those of processes that no longer run, and every writer calls it before it starts, so a
stale temporary never outlives the next run's start. The name carries the writer's host as well
as its process id because a folder may be shared by several machines (a cluster's network file
system): a process id means something only on its own host, so a temporary of another host is
never judged stale here (it may be a live write there); only that host's next writer, or a
person, removes it. Temporaries named ``<name>.tmp-<pid>`` (written before the host was part of
the name) are judged by the process id on this host, as they always were.
"""

from __future__ import annotations

import errno
import os
import re
import socket
from pathlib import Path
from typing import TextIO

__all__ = ["temporary_path", "remove_stale_temporaries", "same_file", "host_name", "open_no_follow", "write_atomic"]


def host_name() -> str:
    """This machine's name as it appears in temporary names: characters other than letters,
    digits, ``.``, ``_`` and ``-`` become ``_`` (the pid follows the last ``-``)."""
    return re.sub(r"[^A-Za-z0-9._-]", "_", socket.gethostname()) or "host"


def temporary_path(path: str | os.PathLike) -> Path:
    """``<path>.tmp-<this host>-<this pid>``: where a writer puts the file until it is complete."""
    path = Path(path)
    return path.with_name(f"{path.name}.tmp-{host_name()}-{os.getpid()}")


def _writer(suffix: str) -> tuple[str | None, int] | None:
    """(host, pid) of the writer named by a temporary's suffix (after ``.tmp-``): ``HOST-PID``,
    or the older ``PID`` (host None); None for any other name."""
    host, sep, pid = suffix.rpartition("-")
    if not pid.isdigit():
        return None
    return (host if sep else None), int(pid)


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
    """Delete the temporaries of ``path`` left by writers of this host that no longer run (a
    killed write); returns the files removed. Temporaries of live processes (a concurrent writer)
    and of other hosts stay."""
    path = Path(path)
    if not path.parent.is_dir():
        return []
    removed = []
    prefix = f"{path.name}.tmp-"
    here = host_name()
    for candidate in path.parent.glob(f"{path.name}.tmp-*"):
        writer = _writer(candidate.name[len(prefix):])
        if writer is None or not candidate.is_file():
            continue
        host, pid = writer
        if (host is not None and host != here) or _running(pid):
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


def _no_follow_fd(path: Path, flags: int) -> int:
    """``os.open`` that refuses a symbolic link at ``path`` (a link planted where an output goes
    must not redirect the write onto whatever it points at)."""
    try:
        return os.open(path, flags | getattr(os, "O_NOFOLLOW", 0) | getattr(os, "O_CLOEXEC", 0), 0o644)
    except OSError as err:
        if err.errno == errno.ELOOP or os.path.islink(path):
            raise FileExistsError(f"{path}: is a symbolic link; refusing to write through it (remove the link, "
                                  "or write elsewhere)") from None
        raise


def open_no_follow(path: str | os.PathLike, mode: str = "a") -> TextIO:
    """A file opened for writing (``"w"``: truncated, ``"a"``: appended, ``"x"``: new; a ``"b"``
    suffix for bytes) that is never a symbolic link: a planted link raises FileExistsError naming
    the path."""
    kind, binary = mode.rstrip("b"), mode.endswith("b")
    flags = {"w": os.O_WRONLY | os.O_CREAT | os.O_TRUNC, "a": os.O_WRONLY | os.O_CREAT | os.O_APPEND,
             "x": os.O_WRONLY | os.O_CREAT | os.O_EXCL}[kind]
    return os.fdopen(_no_follow_fd(Path(path), flags), (kind if kind != "x" else "w") + ("b" if binary else ""))


def write_atomic(path: str | os.PathLike, data: str | bytes) -> Path:
    """Write ``data`` to ``path`` whole or not at all: a new temporary (created exclusively, never
    through a link) renamed over ``path``. A symbolic link at ``path`` is replaced by the file,
    not followed."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    remove_stale_temporaries(path)
    tmp = temporary_path(path)
    if os.path.islink(tmp):
        tmp.unlink()
    fd = _no_follow_fd(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data.encode() if isinstance(data, str) else data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
    return path
