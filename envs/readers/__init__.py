"""Readers for event recordings: one interface (:class:`EventReader`), one class per format."""

from envs.readers.base import ArrayReader, EventReader, FlowGT

__all__ = ["ArrayReader", "EventReader", "FlowGT"]
