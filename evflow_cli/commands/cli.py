"""How every command ends on a user's mistake: one line ``error: <message>`` on stderr and exit
status 2 (as argparse does for a bad option), not a traceback.

A user error is one this project raises on purpose about its input: a ``raise`` statement in
``envs/``, ``agents/``, ``losses/`` or ``evflow_cli/`` raising a ``ValueError`` (``FormatError``, ``EventError``,
``CheckpointError``... are ValueErrors) or a missing, existing, unwritable path
(``FileNotFoundError``, ``FileExistsError``, ``IsADirectoryError``, ``NotADirectoryError``,
``PermissionError``). Anything else (a bug, an error raised inside numpy or torch) keeps its
traceback, and ``EVFLOW_DEBUG=1`` shows the traceback of a user error too.

``python scripts/X.py`` runs ``run(main)``; the console commands (``evflow-*``) are listed once,
in ``COMMANDS``, and their functions are made from it: a new command is its module (with
``main(argv)``), one line of ``COMMANDS`` and the same line in pyproject.toml's [project.scripts].
"""

from __future__ import annotations

import errno
import importlib
import linecache
import os
import sys
from pathlib import Path
from typing import Callable

__all__ = ["COMMANDS", "USER_ERRORS", "is_user_error", "run"]

USER_ERRORS = (ValueError, FileNotFoundError, FileExistsError, IsADirectoryError, NotADirectoryError, PermissionError)
_OURS = tuple(str(Path(__file__).resolve().parents[2] / package) + os.sep for package in ("envs", "agents", "losses", "evflow_cli"))


def is_user_error(err: BaseException) -> bool:
    """True for an exception of ``USER_ERRORS`` raised by a ``raise`` statement of this project
    (the innermost frame of its traceback)."""
    if not isinstance(err, USER_ERRORS) or err.__traceback__ is None:
        return False
    tb = err.__traceback__
    while tb.tb_next is not None:
        tb = tb.tb_next
    filename = os.path.realpath(tb.tb_frame.f_code.co_filename)
    return filename.startswith(_OURS) and linecache.getline(filename, tb.tb_lineno).lstrip().startswith("raise")


def disk_full(err: BaseException) -> bool:
    """True for a write that failed because the disk (or the user's quota) is full, however it
    surfaced: an OSError with errno ENOSPC / EDQUOT, or h5py's and torch's own errors that only
    say so in their message (they do not keep the errno)."""
    for e in (err, err.__cause__, err.__context__):
        if isinstance(e, OSError) and e.errno in (errno.ENOSPC, errno.EDQUOT):
            return True
        if isinstance(e, (OSError, RuntimeError)) and ("No space left on device" in str(e) or "errno = 28" in str(e)):
            return True
    return False


def run(main: Callable[[list[str] | None], int], argv: list[str] | None = None) -> int:
    """``main(argv)``'s exit status; a user error (:func:`is_user_error`) prints ``error: <message>``
    to stderr and returns 2, unless the environment sets ``EVFLOW_DEBUG=1``. A full disk
    (:func:`disk_full`) says so in one line and returns 3: the outputs are written to temporaries
    and renamed only when complete (envs.outputs), so the earlier files are still there and no
    partial new one is; free some space and run the command again."""
    debug = os.environ.get("EVFLOW_DEBUG", "") not in ("", "0")
    try:
        return main(argv)
    except (OSError, RuntimeError) as err:
        if debug or not disk_full(err):
            if isinstance(err, USER_ERRORS) and not debug and is_user_error(err):
                print(f"error: {err}", file=sys.stderr)
                return 2
            raise
        name = getattr(err, "filename", None)
        print(f"error: the disk is full{f' writing {name}' if name else ''} ({type(err).__name__}: "
              f"{str(err).splitlines()[0][:200]}); the earlier outputs are unchanged and no partial new one was kept: "
              "free some space and run the command again", file=sys.stderr)
        return 3
    except USER_ERRORS as err:
        if os.environ.get("EVFLOW_DEBUG", "") not in ("", "0") or not is_user_error(err):
            raise
        print(f"error: {err}", file=sys.stderr)
        return 2


#: The console commands: command name -> its module in evflow_cli/commands. pyproject.toml's
#: [project.scripts] names each as ``evflow_cli.commands.cli:<module>`` (tests/test_options.py
#: holds the two equal); the function is made here, on first use, by :func:`__getattr__`.
COMMANDS: dict[str, str] = {
    "evflow-train": "train",
    "evflow-evaluate": "evaluate",
    "evflow-predict": "predict",
    "evflow-convert": "convert",
    "evflow-generate": "generate",
    "evflow-benchmark": "benchmark",
    "evflow-teacher-targets": "teacher_targets",
    "evflow-ship": "ship",
    "evflow-campaign": "campaign",
    "evflow-export": "export_model",
    "evflow-ablations": "ablations",
    "evflow-main": "main_job",
    "evflow-param-counts": "param_counts",
    "evflow-tradeoff": "tradeoff",
}


def _program(command: str) -> Callable[[list[str] | None], int]:
    """The console function of evflow_cli/commands/``command``.py: ``run(main, argv)``; a module
    that defines ``exit_process(status)`` (train: a torchrun rank's end) ends the process through it."""

    def entry(argv: list[str] | None = None) -> int:
        module = importlib.import_module(f"evflow_cli.commands.{command}")
        status = run(module.main, argv)
        end = getattr(module, "exit_process", None)
        return status if end is None else end(status)

    entry.__name__ = entry.__qualname__ = command
    entry.__doc__ = f"The console command of evflow_cli/commands/{command}.py."
    return entry


def __getattr__(name: str) -> Callable[[list[str] | None], int]:
    """``evflow_cli.commands.cli.<module>``: the console function of a command of ``COMMANDS``."""
    if name in COMMANDS.values():
        return _program(name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(COMMANDS.values()))
