"""Old address of ``agents.wrappers.mirror`` (kept while ``agents/commands/evaluate.py`` imports
from here; delete once it imports from ``agents.wrappers``)."""

from .wrappers.mirror import MIRROR_SETS, MIRRORS, ROTATION, MirrorPolicy

__all__ = ["MirrorPolicy", "MIRRORS", "ROTATION", "MIRROR_SETS"]
