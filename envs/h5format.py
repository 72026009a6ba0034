"""The project's own recording format ("evflow h5"), under its earlier name.

The writer and the reader live in :mod:`envs.readers.h5` (the layout is described there) and
:class:`FormatError` in :mod:`envs.readers.base`; this module re-exports them so that
``from envs.h5format import H5Reader, H5Writer, FormatError, write_h5`` keeps working.
"""

from envs.readers.base import FormatError
from envs.readers.h5 import FORMAT_NAME, FORMAT_VERSION, H5Reader, H5Writer, write_h5

__all__ = ["H5Writer", "H5Reader", "FormatError", "write_h5", "FORMAT_NAME", "FORMAT_VERSION"]
