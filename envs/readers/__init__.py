"""Readers for event recordings: one interface (:class:`EventReader`), one class per format.

``open_recording(path, format=None, **options)`` opens any supported file (see
:mod:`envs.readers.detect`). The format modules load on first use: ``envs.h5format`` imports
this package, and they import ``envs.h5format``.
"""

from envs.readers.base import ArrayReader, EventReader, FlowGT

__all__ = [
    "ArrayReader",
    "EventReader",
    "FlowGT",
    "open_recording",
    "detect_format",
    "FORMATS",
    "MVSECReader",
    "DSECReader",
    "HagenaarsReader",
    "TextReader",
    "AedatReader",
    "PropheseeRawReader",
    "PropheseeDatReader",
]

_LAZY = {
    "open_recording": "envs.readers.detect",
    "detect_format": "envs.readers.detect",
    "FORMATS": "envs.readers.detect",
    "MVSECReader": "envs.readers.mvsec",
    "DSECReader": "envs.readers.dsec",
    "HagenaarsReader": "envs.readers.hagenaars",
    "TextReader": "envs.readers.text",
    "AedatReader": "envs.readers.aedat",
    "PropheseeRawReader": "envs.readers.prophesee",
    "PropheseeDatReader": "envs.readers.prophesee",
}


def __getattr__(name):
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'envs.readers' has no attribute {name!r}")
