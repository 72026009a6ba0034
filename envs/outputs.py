"""The one guard for every file a command writes (flow files, videos, JSON, tables, pictures).

An :class:`Output` is claimed before any work is done, and the claim refuses, naming the path
(and the option, when given):

- an input of the command (the same file by path, through a symlink or a hard link), even with
  ``overwrite``: a result never replaces what it was computed from;
- a folder; an existing file unless ``overwrite``; a path already claimed for another output of
  the same command (``--json`` equal to ``--out``);
- a destination that cannot be written (its folders are created and its lock file is written
  there at once), so a bad path fails now, not after an hour of work;
- a path another process is writing now: the claim holds ``<name>.lock`` (``flock``, released
  by the kernel when a process dies) until the file is committed or discarded, and a second
  writer fails naming the first's process and temporary file.

The content goes to ``<name>.tmp-<host>-<pid>`` (:attr:`Output.temporary`) and is renamed over the path
by :meth:`Output.commit`, so the file appears whole or not at all; :meth:`Output.discard` (or
leaving the ``with`` block by an exception) removes it, and a killed writer's temporary is
removed at the next claim (:mod:`envs.atomic`).

    with Output(args.json, inputs=[("recording", args.recording)], overwrite=args.overwrite,
                option="--json") as out:
        ...                                  # the work
        out.write_text(json.dumps(summary))  # written and renamed; the lock released
"""

from __future__ import annotations

import errno
import fcntl
import os
from pathlib import Path
from typing import Iterable

from envs.atomic import open_no_follow, remove_stale_temporaries, same_file, temporary_path

__all__ = ["Output", "lock_path", "hold_folder", "release_folder", "folder_holder"]

#: realpath -> what claimed it, for the outputs this process holds now
_CLAIMED: dict[str, str] = {}


def lock_path(path: str | os.PathLike) -> Path:
    """``<path>.lock``: the file a writer of ``path`` holds locked while it writes."""
    path = Path(path)
    return path.with_name(f"{path.name}.lock")


class Output:
    """One file a command writes, claimed at construction (module docstring for the rules).

    path: the file to write. inputs: (what, path) pairs of the command's inputs, e.g.
    ``("recording", "rec.h5")``; None paths are skipped. overwrite: replace an existing file.
    option: the command-line option that named the path (``--video``), for the messages.
    exclusive: hold the lock file and refuse a second claim of the path in this process (False:
    the checks and the temporary only, for caches that concurrent workers may fill alike).
    """

    def __init__(
        self,
        path: str | os.PathLike,
        *,
        inputs: Iterable[tuple[str, str | os.PathLike | None]] = (),
        overwrite: bool = False,
        option: str | None = None,
        exclusive: bool = True,
    ) -> None:
        self.path = Path(path)
        self.where = f"{option} {self.path}" if option else str(self.path)
        self.temporary = temporary_path(self.path)
        self._lock_fd: int | None = None
        self._key: str | None = None
        self._held = False
        self.check_inputs(inputs)
        if self.path.is_dir():
            raise IsADirectoryError(f"{self.where}: is a folder; the output must be a file path "
                                    f"(e.g. {self.path / 'output'})")
        key = os.path.realpath(self.path) if exclusive else None
        if key in _CLAIMED:
            raise FileExistsError(f"{self.where}: is also {_CLAIMED[key]} of this command; give each output its own path")
        if self.path.exists() and not overwrite:
            raise FileExistsError(f"{self.where}: exists; pass overwrite=True (--overwrite) to replace it")
        self._made = [f for f in (self.path.parent, *self.path.parent.parents) if not f.exists()]  # deepest first
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
        except OSError as err:
            raise type(err)(f"{self.where}: cannot create its folder {self.path.parent}: {err.strerror}") from None
        if exclusive:
            self._lock_fd = self._lock()
        elif not os.access(self.path.parent, os.W_OK | os.X_OK):
            raise PermissionError(f"{self.where}: cannot write in the folder {self.path.parent}")
        remove_stale_temporaries(self.path)
        if os.path.islink(self.temporary):  # a link planted at our temporary's name: never written through
            self.temporary.unlink()
        self._held = True
        if key is not None:
            self._key = key
            _CLAIMED[key] = self.where

    def check_inputs(self, inputs: Iterable[tuple[str, str | os.PathLike | None]]) -> None:
        """FileExistsError when the path is one of ``inputs`` ((what, path) pairs; None skipped)
        by path, symlink or hard link: also for inputs known only once the claim is held."""
        for what, used in inputs:
            if used is not None and Path(used).exists() and same_file(self.path, used):
                raise FileExistsError(f"{self.where}: is the input {what} {used}; write the output to another file")

    def _lock(self) -> int:
        """Hold ``<name>.lock`` (flock); a lock held by another process raises FileExistsError."""
        lock = lock_path(self.path)
        while True:
            try:
                fd = os.open(lock, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW, 0o644)  # a planted link is refused
            except OSError as err:
                if err.errno == errno.ELOOP:
                    raise FileExistsError(f"{self.where}: its lock {lock} is a symbolic link; refusing to write "
                                          "through it (remove the link)") from None
                raise type(err)(f"{self.where}: cannot write in the folder {self.path.parent}: {err.strerror}") from None
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                # the holder wrote its pid and its temporary's name (which names its host)
                lines = os.read(fd, 4096).decode(errors="replace").split()
                os.close(fd)
                holder = lines[0] if lines else "?"
                temporary = lines[1] if len(lines) > 1 else f"{self.path.name}.tmp-*-{holder}"
                raise FileExistsError(
                    f"{self.where}: another process (pid {holder}) is writing it now, to "
                    f"{temporary}; wait for it to finish or write elsewhere"
                ) from None
            try:  # the previous holder may have removed the file between our open and flock
                held = os.path.samestat(os.fstat(fd), os.stat(lock))
            except FileNotFoundError:
                held = False
            if held:
                os.ftruncate(fd, 0)
                os.write(fd, f"{os.getpid()}\n{self.temporary.name}\n".encode())
                return fd
            os.close(fd)

    def _release(self) -> None:
        self._held = False
        if self._lock_fd is not None:
            lock_path(self.path).unlink(missing_ok=True)
            os.close(self._lock_fd)
            self._lock_fd = None
        if self._key is not None:
            _CLAIMED.pop(self._key, None)
            self._key = None

    @property
    def held(self) -> bool:
        """True until the output is committed, discarded or released."""
        return self._held

    def commit(self) -> Path:
        """Rename the temporary over the path (when the writer left one there), release the claim."""
        try:
            if self.temporary.exists():
                os.replace(self.temporary, self.path)
        finally:
            self._release()
        return self.path

    def discard(self) -> None:
        """Remove the temporary and release the claim; the path is left as it was, and the folders
        this output created are removed again while empty (a failed run leaves no empty folder)."""
        try:
            self.temporary.unlink(missing_ok=True)
        finally:
            self._release()
            for folder in self._made:
                try:
                    folder.rmdir()  # only while empty: another output's file keeps it
                except OSError:
                    break

    def release(self) -> None:
        """Release the claim of a writer that wrote the path itself (its own temporary and rename:
        ``save_animation``, ``save_png``), or that wrote nothing."""
        self._release()

    def write_text(self, text: str) -> Path:
        """Write ``text`` to the temporary and commit it."""
        with open_no_follow(self.temporary, "w") as f:
            f.write(text)
        return self.commit()

    def __enter__(self) -> "Output":
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if not self.held:
            return
        if exc_type is None:
            self.commit()
        else:
            self.discard()

    def __del__(self) -> None:  # a claim dropped without commit or discard: let another writer in
        try:
            self._release()
        except Exception:
            pass


#: the folder locks this process holds (kept open for its life; the kernel releases them at exit)
_FOLDER_LOCKS: dict[str, int] = {}


def hold_folder(folder: str | os.PathLike, option: str = "--out") -> Path:
    """Make this process the one writer of ``folder`` (a run folder, a campaign's work folder)
    for the rest of its life: ``FOLDER/writer.lock`` held with ``flock``, which the kernel
    releases when the process ends however it ends (no stale pid file). A second process gets
    FileExistsError naming the first's pid; a symbolic link at the lock's place is refused."""
    folder = Path(folder)
    key = os.path.realpath(folder)
    lock = folder / "writer.lock"
    if key in _FOLDER_LOCKS:
        return lock
    folder.mkdir(parents=True, exist_ok=True)
    try:
        fd = os.open(lock, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW | os.O_CLOEXEC, 0o644)
    except OSError as err:
        if err.errno == errno.ELOOP:
            raise FileExistsError(f"{option} {folder}: {lock.name} is a symbolic link; refusing to write through it") from None
        raise type(err)(f"{option} {folder}: cannot write in it: {err.strerror}") from None
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        holder = os.read(fd, 64).decode(errors="replace").strip() or "?"
        os.close(fd)
        raise FileExistsError(f"{option} {folder}: another process (pid {holder}) is writing this folder now; "
                              "wait for it to finish, stop it, or write elsewhere") from None
    os.ftruncate(fd, 0)
    os.write(fd, f"{os.getpid()}\n".encode())
    _FOLDER_LOCKS[key] = fd
    return lock


def release_folder(folder: str | os.PathLike) -> None:
    """Give up :func:`hold_folder`'s lock of ``folder`` (no-op when this process does not hold it)."""
    fd = _FOLDER_LOCKS.pop(os.path.realpath(folder), None)
    if fd is not None:
        os.close(fd)


def folder_holder(folder: str | os.PathLike) -> int | None:
    """The pid of the process holding ``folder``'s writer lock now, or None when nobody holds it
    (the lock is free: its last holder died or finished)."""
    lock = Path(folder) / "writer.lock"
    if os.path.realpath(folder) in _FOLDER_LOCKS:
        return os.getpid()
    try:
        fd = os.open(lock, os.O_RDONLY | os.O_NOFOLLOW | os.O_CLOEXEC)
    except OSError:
        return None
    try:
        fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
    except BlockingIOError:
        text = os.read(fd, 64).decode(errors="replace").strip()
        return int(text) if text.isdigit() else -1
    finally:
        os.close(fd)
    return None
