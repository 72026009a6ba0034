"""Old address of ``agents.wrappers.subwindows`` (kept while ``agents/commands/evaluate.py``
imports from here; delete once it imports from ``agents.wrappers``)."""

from .wrappers.subwindows import SubWindowPolicy, compose_flows, sub_windows

__all__ = ["SubWindowPolicy", "compose_flows", "sub_windows"]
