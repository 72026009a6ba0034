"""Where the project keeps what it can rebuild: ``$EVFLOW_CACHE``, default ``~/.cache/evflow``.

Its users each keep a subfolder: the simulated sequences (:mod:`envs.synthetic`, ``synthetic/``)
and the time indexes of Prophesee recordings (:mod:`envs.readers.prophesee`,
``prophesee-index/``). ``EVFLOW_CACHE=off`` (or ``0``, ``none``, empty) turns the disk cache off.
"""

from __future__ import annotations

import os
from pathlib import Path

__all__ = ["cache_root"]


def cache_root() -> Path | None:
    """The on-disk cache folder ($EVFLOW_CACHE or ~/.cache/evflow), None when set to 'off'."""
    root = os.environ.get("EVFLOW_CACHE", str(Path.home() / ".cache" / "evflow"))
    if root.strip().lower() in ("", "off", "0", "none"):
        return None
    return Path(root).expanduser()
