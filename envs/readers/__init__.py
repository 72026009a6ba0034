"""Readers for event recordings: one interface (:class:`EventReader`), one class per format.

``open_recording(path, format=None, **options)`` opens any supported file (see
:mod:`envs.readers.detect`). The package owns its errors (:class:`FormatError`, in
:mod:`envs.readers.base`) and the project's own h5 reader and writer (:mod:`envs.readers.h5`);
it imports nothing of ``envs`` but :mod:`envs.events`, :mod:`envs.outputs` and :mod:`envs.cache`.
"""

from envs.readers.aedat import AedatReader
from envs.readers.base import ArrayReader, EventReader, FlowGT, FormatError
from envs.readers.detect import FORMATS, detect_format, open_recording
from envs.readers.dsec import DSECReader
from envs.readers.h5 import H5Reader, H5Writer, write_h5
from envs.readers.hagenaars import HagenaarsReader
from envs.readers.mvsec import MVSECReader
from envs.readers.prophesee import PropheseeDatReader, PropheseeRawReader
from envs.readers.text import TextReader

__all__ = [
    "ArrayReader",
    "EventReader",
    "FlowGT",
    "FormatError",
    "H5Reader",
    "H5Writer",
    "write_h5",
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
