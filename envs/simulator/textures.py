"""Procedural textures with natural-image statistics, made in numpy (no downloads).

A texture is a periodic (tiling) square of log intensities, so sampling it at any real
coordinate wraps around and nothing ever runs out of texture. The model is *dead leaves*
(Matheron; Lee, Mumford & Huang 2001): opaque discs with radii drawn from ``p(r) ~ r^-3``
(scale invariance, hence the ~1/f^2 power spectrum of natural images) dropped one on top of
the other at uniform random positions, each with a uniform random log intensity. A faint
low-frequency ``1/f`` shading field is added (smooth illumination changes inside leaves), and
the result is blurred once with a Gaussian so that sampling it at sub-pixel positions and
moderate minification does not alias (aliasing would dominate the events).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["TextureConfig", "PeriodicTexture", "dead_leaves", "make_texture", "sample_wrapped"]


@dataclass(frozen=True)
class TextureConfig:
    """How a dead-leaves texture is made.

    r_min, r_max: leaf radii range in texture pixels (1 texture px = 1 image px at scale 1).
    log_min, log_max: range of leaf log intensities (natural log; 2.5 = a 12:1 contrast).
    coverage: expected number of leaves covering a point (4 leaves: 98 % covered).
    shading: standard deviation of the low-frequency shading field, log units.
    blur_sigma: Gaussian anti-aliasing blur, texture pixels.
    """

    r_min: float = 2.0
    r_max: float = 64.0
    log_min: float = -2.5
    log_max: float = 0.0
    coverage: float = 4.0
    shading: float = 0.15
    blur_sigma: float = 0.8


def _leaf_radii(rng: np.random.Generator, n: int, r_min: float, r_max: float) -> np.ndarray:
    """n radii with density ~ r^-3 on [r_min, r_max] (inverse-CDF sampling)."""
    a, b = r_min**-2.0, r_max**-2.0
    return (a - rng.random(n) * (a - b)) ** -0.5


def dead_leaves(rng: np.random.Generator, size: int, config: TextureConfig = TextureConfig()) -> np.ndarray:
    """A periodic dead-leaves image: (size, size) float32 log intensities, size a power of two.

    Leaves are painted back to front (leaf i+1 covers leaf i): every pixel takes the value of
    the highest-numbered leaf covering it, found with one ``np.maximum.at`` per radius class.
    """
    if size & (size - 1):
        raise ValueError(f"texture size must be a power of two, got {size}")
    mask = size - 1
    r_min, r_max = config.r_min, min(config.r_max, size / 4)
    mean_r2 = 2.0 * np.log(r_max / r_min) / (r_min**-2.0 - r_max**-2.0)  # E[r^2] under r^-3
    n = int(np.ceil(config.coverage * size * size / (np.pi * mean_r2)))
    radii = _leaf_radii(rng, n, r_min, r_max)
    cx, cy = rng.uniform(0, size, (2, n))
    values = rng.uniform(config.log_min, config.log_max, n).astype(np.float32)

    owner = np.full(size * size, -1, np.int64)
    half = np.ceil(radii).astype(np.int64)
    for h in np.unique(half):
        leaves = np.flatnonzero(half == h)
        offsets = np.arange(-h, h + 1)
        dy, dx = (a.ravel() for a in np.meshgrid(offsets, offsets, indexing="ij"))
        # bound the temporary arrays to ~4M entries
        per_chunk = max(1, (1 << 22) // len(dx))
        for i0 in range(0, len(leaves), per_chunk):
            ids = leaves[i0 : i0 + per_chunk]
            px = np.rint(cx[ids]).astype(np.int64)[:, None] + dx
            py = np.rint(cy[ids]).astype(np.int64)[:, None] + dy
            inside = (px - cx[ids, None]) ** 2 + (py - cy[ids, None]) ** 2 <= radii[ids, None] ** 2
            flat = ((py & mask) * size + (px & mask))[inside]
            np.maximum.at(owner, flat, np.broadcast_to(ids[:, None], inside.shape)[inside])
    background = np.float32(0.5 * (config.log_min + config.log_max))
    image = np.where(owner >= 0, values[np.maximum(owner, 0)], background)
    return image.reshape(size, size).astype(np.float32)


def make_texture(rng: np.random.Generator, size: int, config: TextureConfig = TextureConfig()) -> np.ndarray:
    """Dead leaves + 1/f shading, Gaussian-blurred: (size, size) float32 periodic log intensity."""
    leaves = dead_leaves(rng, size, config)
    fy = np.fft.fftfreq(size)[:, None]
    fx = np.fft.rfftfreq(size)[None, :]
    f2 = fx**2 + fy**2
    spectrum = np.fft.rfft2(leaves)
    if config.shading > 0:
        noise = np.fft.rfft2(rng.standard_normal((size, size)))
        f = np.sqrt(f2)
        f[0, 0] = np.inf  # no DC offset
        shading = np.fft.irfft2(noise / (f * size), s=(size, size))
        spectrum += np.fft.rfft2(shading * (config.shading / max(shading.std(), 1e-12)))
    spectrum *= np.exp(-2.0 * np.pi**2 * config.blur_sigma**2 * f2)  # Gaussian blur (periodic)
    return np.fft.irfft2(spectrum, s=(size, size)).astype(np.float32)


def sample_wrapped(texture: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Bilinear sample of a periodic texture at real coordinates.

    texture: (S, S) float32, S a power of two; u (column), v (row): float arrays of one shape,
    any real values (they wrap modulo S). Returns float32 of the same shape.
    For repeated sampling use :class:`PeriodicTexture` (pads once).
    """
    return PeriodicTexture(texture).sample(u, v)


class PeriodicTexture:
    """A periodic texture prepared for fast bilinear sampling: one wrapped row and column are
    appended, so the four neighbours of any texel are at fixed flat offsets (no wrapping per
    neighbour).

    texture: (S, S) float32, S a power of two.
    """

    def __init__(self, texture: np.ndarray) -> None:
        size = texture.shape[0]
        if texture.shape != (size, size) or size & (size - 1):
            raise ValueError(f"texture must be square with a power-of-two side, got {texture.shape}")
        self.size = size
        self.texture = texture
        self._flat = np.pad(texture.astype(np.float32), ((0, 1), (0, 1)), mode="wrap").ravel()

    def sample(self, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        """Bilinear sample at (u, v) = (column, row), wrapping modulo S: float32, u's shape."""
        mask = self.size - 1
        u0 = np.floor(u)
        v0 = np.floor(v)
        fu = (u - u0).astype(np.float32, copy=False)
        fv = (v - v0).astype(np.float32, copy=False)
        i00 = (v0.astype(np.int32) & mask) * (self.size + 1) + (u0.astype(np.int32) & mask)
        flat = self._flat
        a = flat.take(i00)
        b = flat.take(i00 + 1)
        i00 += self.size + 1
        c = flat.take(i00)
        d = flat.take(i00 + 1)
        top = a + fu * (b - a)
        bottom = c + fu * (d - c)
        return top + fv * (bottom - top)
