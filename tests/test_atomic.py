"""envs/atomic.py: temporaries named by host and process id, and which ones a writer may delete."""

from __future__ import annotations

import os
import subprocess
import sys

from envs.atomic import host_name, remove_stale_temporaries, temporary_path


def _dead_pid() -> int:
    done = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    return int(done.stdout)


def test_a_temporary_names_this_host_and_process(tmp_path):
    path = temporary_path(tmp_path / "checkpoint.pt")
    assert path.parent == tmp_path and path.name == f"checkpoint.pt.tmp-{host_name()}-{os.getpid()}"
    assert "/" not in host_name() and host_name()


def test_only_temporaries_of_this_host_whose_writer_is_gone_are_removed(tmp_path):
    """On a folder shared by several machines a process id says nothing about another host's
    process: a dead pid there may be a live writer. Older names without a host are judged here."""
    target = tmp_path / "out.h5"
    dead, alive, here = _dead_pid(), os.getppid(), host_name()
    files = {
        "mine, dead": tmp_path / f"out.h5.tmp-{here}-{dead}",
        "mine, alive": tmp_path / f"out.h5.tmp-{here}-{alive}",
        "other host, dead pid": tmp_path / f"out.h5.tmp-node-17.cluster-{dead}",
        "older name, dead": tmp_path / f"out.h5.tmp-{dead}",
        "older name, alive": tmp_path / f"out.h5.tmp-{alive}",
        "not a temporary": tmp_path / "out.h5.tmp-notes",
        "another target": tmp_path / f"other.h5.tmp-{here}-{dead}",
    }
    for path in files.values():
        path.write_bytes(b"x")
    removed = remove_stale_temporaries(target)
    assert sorted(removed) == sorted([files["mine, dead"], files["older name, dead"]])
    assert {name for name, path in files.items() if path.exists()} == {
        "mine, alive", "other host, dead pid", "older name, alive", "not a temporary", "another target"}
