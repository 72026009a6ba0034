"""Minimal PNG codec for 8/16-bit grayscale, RGB and RGBA images (no palette, no interlace).

Why here: DSEC stores its flow ground truth as 16-bit RGB PNGs, and Pillow reads those as
8-bit RGB (it drops the low byte), which would destroy the 1/128-pixel flow resolution. Decoding
is numpy-vectorised: rows whose filters are None/Sub/Up are undone row by row, and images with
Average or Paeth rows are undone along anti-diagonals (pixel (r, c) depends only on (r, c-1),
(r-1, c) and (r-1, c-1), so each anti-diagonal is one vector step).
"""

from __future__ import annotations

import os
import struct
import zlib

import numpy as np

__all__ = ["read_png", "write_png", "png_size", "PNGError"]

_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_CHANNELS = {0: 1, 2: 3, 4: 2, 6: 4}  # colour type -> channels (gray, RGB, gray+alpha, RGBA)


class PNGError(ValueError):
    """A PNG this codec cannot read; the message names the file and the reason."""


def png_size(path: str | os.PathLike) -> tuple[int, int]:
    """(height, width) from a PNG's header, without decoding the image."""
    with open(path, "rb") as f:
        head = f.read(24)
    if head[:8] != _SIGNATURE or head[12:16] != b"IHDR":
        raise PNGError(f"{path}: not a PNG file")
    width, height = struct.unpack(">II", head[16:24])
    return int(height), int(width)


def read_png(path: str | os.PathLike) -> np.ndarray:
    """Read a PNG: (H, W) or (H, W, C) uint8 or uint16 (16-bit samples stay 16-bit)."""
    with open(path, "rb") as f:
        data = f.read()
    if data[:8] != _SIGNATURE:
        raise PNGError(f"{path}: not a PNG file")
    pos, idat, header = 8, [], None
    while pos < len(data):
        (length,) = struct.unpack(">I", data[pos : pos + 4])
        kind = data[pos + 4 : pos + 8]
        body = data[pos + 8 : pos + 8 + length]
        pos += 12 + length
        if kind == b"IHDR":
            header = struct.unpack(">IIBBBBB", body)
        elif kind == b"IDAT":
            idat.append(body)
        elif kind == b"IEND":
            break
    if header is None:
        raise PNGError(f"{path}: no IHDR chunk")
    width, height, depth, colour, _, _, interlace = header
    if colour not in _CHANNELS or depth not in (8, 16) or interlace:
        raise PNGError(f"{path}: unsupported PNG (bit depth {depth}, colour type {colour}, interlace {interlace})")
    channels = _CHANNELS[colour]
    bpp = channels * depth // 8
    raw = np.frombuffer(zlib.decompress(b"".join(idat)), np.uint8)
    stride = width * bpp + 1
    if raw.size != height * stride:
        raise PNGError(f"{path}: image data has {raw.size} bytes, expected {height * stride}")
    rows = raw.reshape(height, stride)
    filters = rows[:, 0]
    if (filters > 4).any():
        raise PNGError(f"{path}: unknown row filter {int(filters.max())}")
    pixels = _unfilter(rows[:, 1:].reshape(height, width, bpp), filters)
    if depth == 16:
        out = pixels.reshape(height, width * channels * 2).view(">u2").astype(np.uint16)
    else:
        out = pixels.reshape(height, width * channels)
    out = out.reshape(height, width, channels)
    return out[:, :, 0] if channels == 1 else out


def _unfilter(filt: np.ndarray, filters: np.ndarray) -> np.ndarray:
    """Undo PNG row filters: filt (H, W, bpp) uint8 filtered bytes -> (H, W, bpp) uint8."""
    h, w, bpp = filt.shape
    out = np.zeros((h + 1, w + 1, bpp), np.int32)  # a zero row above and a zero column left
    f = filt.astype(np.int32)
    if not np.isin(filters, (3, 4)).any():
        for r in range(h):
            kind = filters[r]
            if kind == 0:
                out[r + 1, 1:] = f[r]
            elif kind == 1:
                out[r + 1, 1:] = np.cumsum(f[r], axis=0) & 255
            else:
                out[r + 1, 1:] = (f[r] + out[r, 1:]) & 255
        return out[1:, 1:].astype(np.uint8)
    kinds = filters.astype(np.int64)
    for d in range(h + w - 1):  # anti-diagonals r + c = d
        r = np.arange(max(0, d - w + 1), min(d, h - 1) + 1)
        c = d - r
        a = out[r + 1, c]  # left
        b = out[r, c + 1]  # up
        ul = out[r, c]  # up-left
        k = kinds[r][:, None]
        p = a + b - ul
        pa, pb, pc = np.abs(p - a), np.abs(p - b), np.abs(p - ul)
        paeth = np.where((pa <= pb) & (pa <= pc), a, np.where(pb <= pc, b, ul))
        pred = np.select([k == 0, k == 1, k == 2, k == 3], [0, a, b, (a + b) >> 1], paeth)
        out[r + 1, c + 1] = (f[r, c] + pred) & 255
    return out[1:, 1:].astype(np.uint8)


def write_png(path: str | os.PathLike, image: np.ndarray, *, filters: int | list[int] = 0) -> None:
    """Write (H, W) / (H, W, C) uint8 or uint16 as PNG. filters: one PNG filter type (0-4) for all
    rows or one per row (tests use this to exercise every filter of the decoder)."""
    image = np.asarray(image)
    if image.dtype not in (np.uint8, np.uint16):
        raise PNGError(f"{path}: write_png takes uint8 or uint16, got {image.dtype}")
    if image.ndim == 2:
        image = image[:, :, None]
    height, width, channels = image.shape
    colour = {1: 0, 3: 2, 2: 4, 4: 6}[channels]
    depth = 16 if image.dtype == np.uint16 else 8
    data = image.astype(">u2").tobytes() if depth == 16 else image.tobytes()
    bpp = channels * depth // 8
    px = np.frombuffer(data, np.uint8).reshape(height, width, bpp).astype(np.int32)
    kinds = np.broadcast_to(np.asarray(filters), (height,))
    a = np.zeros_like(px)
    a[:, 1:] = px[:, :-1]
    b = np.zeros_like(px)
    b[1:] = px[:-1]
    ul = np.zeros_like(px)
    ul[1:, 1:] = px[:-1, :-1]
    p = a + b - ul
    pa, pb, pc = np.abs(p - a), np.abs(p - b), np.abs(p - ul)
    paeth = np.where((pa <= pb) & (pa <= pc), a, np.where(pb <= pc, b, ul))
    preds = [np.zeros_like(px), a, b, (a + b) >> 1, paeth]
    rows = [bytes([int(k)]) + ((px[r] - preds[int(k)][r]) & 255).astype(np.uint8).tobytes() for r, k in enumerate(kinds)]

    def chunk(kind: bytes, body: bytes) -> bytes:
        return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body) & 0xFFFFFFFF)

    with open(path, "wb") as fh:
        fh.write(_SIGNATURE)
        fh.write(chunk(b"IHDR", struct.pack(">IIBBBBB", width, height, depth, colour, 0, 0, 0)))
        fh.write(chunk(b"IDAT", zlib.compress(b"".join(rows), 6)))
        fh.write(chunk(b"IEND", b""))
