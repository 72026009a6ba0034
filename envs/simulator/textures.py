"""Procedural textures with natural-image statistics, made in numpy (no downloads).

A texture is a periodic (tiling) square of log intensities, so sampling it at any real
coordinate wraps around and nothing ever runs out of texture. The model is *dead leaves*
(Matheron; Lee, Mumford & Huang 2001): opaque discs with radii drawn from ``p(r) ~ r^-3``
(scale invariance, hence the ~1/f^2 power spectrum of natural images) dropped one on top of
the other at uniform random positions, each with a uniform random log intensity. A faint
low-frequency ``1/f`` shading field is added (smooth illumination changes inside leaves), and
the result is blurred once with a Gaussian so that sampling it at sub-pixel positions and
moderate minification does not alias (aliasing would dominate the events).

Other families (``TextureConfig.family``; the domain-randomised splits draw them): ``noise``
(Gaussian noise with a ``1/f^exponent`` amplitude spectrum), ``edges`` (opaque oriented bars
around one orientation), ``lines`` (thin oriented lines on a plain ground), ``checker``
(square cells, each its own level), ``glyphs`` (rows of random 3x5 stroke glyphs, text-like),
``gradient`` (very smooth, ``1/f^3``), ``flat`` (one level: a blank wall or a dark ground),
``dots`` (sparse discs on a plain ground), ``plaid`` (two sine gratings) and ``natural``
(textured dead leaves: the r^-3 leaves above, each showing its own amount of a shared
``1/f^exponent`` noise, so that surfaces are textured inside as well as at their edges, like
grass, gravel or foliage in photographs, whose amplitude spectra fall as ~1/f and whose
gradients are heavy-tailed). Each draws a pattern in [0, 1] that is mapped
onto [log_min, log_max]; shading and blur follow as above.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal, get_args

import numpy as np

__all__ = ["TextureConfig", "TextureFamily", "PeriodicTexture", "dead_leaves", "make_texture", "sample_wrapped"]

TextureFamily = Literal["dead_leaves", "noise", "edges", "lines", "checker", "glyphs", "gradient", "flat", "dots", "plaid", "natural"]


@dataclass(frozen=True)
class TextureConfig:
    """How a dead-leaves texture is made.

    r_min, r_max: leaf radii range in texture pixels (1 texture px = 1 image px at scale 1).
    log_min, log_max: range of leaf log intensities (natural log; 2.5 = a 12:1 contrast).
    coverage: expected number of leaves covering a point (4 leaves: 98 % covered).
    shading: standard deviation of the low-frequency shading field, log units.
    blur_sigma: Gaussian anti-aliasing blur, texture pixels.
    family: the pattern (module docstring); r_min, r_max and coverage apply to dead leaves
        (``dead_leaves`` and ``natural``).
    scale: the other families' feature size, texture pixels (bar width, line spacing, cell,
        glyph stroke x 4, dot radius x 2, grating period / 2).
    orientation, orientation_spread: edges' and lines' mean angle and its normal spread, rad.
    exponent: the amplitude-spectrum exponent of ``noise`` and of ``natural``'s leaf texture
        (1 = natural-image-like).
    """

    r_min: float = 2.0
    r_max: float = 64.0
    log_min: float = -2.5
    log_max: float = 0.0
    coverage: float = 4.0
    shading: float = 0.15
    blur_sigma: float = 0.8
    family: TextureFamily = "dead_leaves"
    scale: float = 8.0
    orientation: float = 0.0
    orientation_spread: float = 0.3
    exponent: float = 1.0

    def __post_init__(self) -> None:
        if self.family not in get_args(TextureFamily):
            raise ValueError(f"TextureConfig.family must be one of {get_args(TextureFamily)}, got {self.family!r}")


def _leaf_radii(rng: np.random.Generator, n: int, r_min: float, r_max: float) -> np.ndarray:
    """n radii with density ~ r^-3 on [r_min, r_max] (inverse-CDF sampling)."""
    a, b = r_min**-2.0, r_max**-2.0
    return (a - rng.random(n) * (a - b)) ** -0.5


def _leaf_owner(rng: np.random.Generator, size: int, config: TextureConfig) -> tuple[np.ndarray, int]:
    """Dead leaves dropped on a periodic (size, size) canvas: (size * size,) int64, the index of
    the top leaf at each pixel (-1: none), and the number of leaves n.

    Leaves are painted back to front (leaf i+1 covers leaf i): every pixel takes the
    highest-numbered leaf covering it, found with one ``np.maximum.at`` per radius class.
    """
    if size & (size - 1):
        raise ValueError(f"texture size must be a power of two, got {size}")
    mask = size - 1
    r_max = min(config.r_max, size / 4)
    r_min = min(config.r_min, r_max / 2)  # a small canvas (an object's) caps large leaves
    mean_r2 = 2.0 * np.log(r_max / r_min) / (r_min**-2.0 - r_max**-2.0)  # E[r^2] under r^-3
    n = int(np.ceil(config.coverage * size * size / (np.pi * mean_r2)))
    radii = _leaf_radii(rng, n, r_min, r_max)
    cx, cy = rng.uniform(0, size, (2, n))

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
    return owner, n


def dead_leaves(rng: np.random.Generator, size: int, config: TextureConfig = TextureConfig()) -> np.ndarray:
    """A periodic dead-leaves image: (size, size) float32 log intensities, size a power of two,
    each leaf one uniform random level in [log_min, log_max]."""
    owner, n = _leaf_owner(rng, size, config)
    values = rng.uniform(config.log_min, config.log_max, n).astype(np.float32)
    background = np.float32(0.5 * (config.log_min + config.log_max))
    image = np.where(owner >= 0, values[np.maximum(owner, 0)], background)
    return image.reshape(size, size).astype(np.float32)


def make_texture(rng: np.random.Generator, size: int, config: TextureConfig = TextureConfig()) -> np.ndarray:
    """The family's pattern (dead leaves by default) + 1/f shading, Gaussian-blurred:
    (size, size) float32 periodic log intensity."""
    if config.family == "dead_leaves":
        leaves = dead_leaves(rng, size, config)
    else:
        pattern = _PATTERNS[config.family](rng, size, config)
        leaves = (config.log_min + pattern * (config.log_max - config.log_min)).astype(np.float32)
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


def _paint(size: int, cx: np.ndarray, cy: np.ndarray, half: np.ndarray, inside) -> np.ndarray:
    """Paint shapes back to front on a periodic (size, size) canvas: (size * size,) int64, the
    index of the last shape covering each pixel (-1: none).

    cx, cy: (n,) centres; half: (n,) int64 half-size of each shape's bounding square;
    inside(ids, dx, dy): bool (len(ids), K), whether the offsets (dx, dy) from the centres of
    shapes ``ids`` lie inside them.
    """
    mask = size - 1
    owner = np.full(size * size, -1, np.int64)
    for h in np.unique(half):
        shapes = np.flatnonzero(half == h)
        offsets = np.arange(-h, h + 1)
        dy, dx = (a.ravel() for a in np.meshgrid(offsets, offsets, indexing="ij"))
        per_chunk = max(1, (1 << 22) // len(dx))  # bound the temporaries to ~4M entries
        for i0 in range(0, len(shapes), per_chunk):
            ids = shapes[i0 : i0 + per_chunk]
            px = np.rint(cx[ids]).astype(np.int64)[:, None] + dx
            py = np.rint(cy[ids]).astype(np.int64)[:, None] + dy
            hit = inside(ids, px - cx[ids, None], py - cy[ids, None])
            flat = ((py & mask) * size + (px & mask))[hit]
            np.maximum.at(owner, flat, np.broadcast_to(ids[:, None], hit.shape)[hit])
    return owner


def _bars(rng: np.random.Generator, size: int, config: TextureConfig, *, thin: bool) -> np.ndarray:
    """Oriented rectangles around config.orientation: wide opaque bars covering the canvas
    (edges) or thin lines on a plain ground covering ~15 % of it (lines). Pattern in [0, 1]."""
    s = config.scale
    if thin:
        half_len = s * rng.uniform(2.0, 8.0, 1 << 16)
        half_wid = rng.uniform(0.35, 0.9, 1 << 16)
        density = 0.15
    else:
        half_len = s * rng.uniform(1.5, 6.0, 1 << 16)
        half_wid = s * rng.uniform(0.25, 1.0, 1 << 16)
        density = 3.0
    area = 4.0 * half_len * half_wid
    n = int(np.searchsorted(np.cumsum(area), density * size * size)) + 1
    half_len, half_wid = half_len[:n], half_wid[:n]
    angle = config.orientation + config.orientation_spread * rng.standard_normal(n)
    cx, cy = rng.uniform(0, size, (2, n))
    values = rng.uniform(0.0, 1.0, n)
    cos, sin = np.cos(angle), np.sin(angle)
    half = np.minimum(np.ceil(np.hypot(half_len, half_wid)), size // 2 - 1).astype(np.int64)

    def inside(ids, dx, dy):
        along = dx * cos[ids, None] + dy * sin[ids, None]
        across = -dx * sin[ids, None] + dy * cos[ids, None]
        return (np.abs(along) <= half_len[ids, None]) & (np.abs(across) <= half_wid[ids, None])

    owner = _paint(size, cx, cy, half, inside)
    ground = float(rng.uniform(0.0, 1.0)) if thin else 0.5
    if thin:  # lines stand out from the ground: the far half of the range
        values = np.where(ground < 0.5, rng.uniform(0.6, 1.0, n), rng.uniform(0.0, 0.4, n))
    return np.where(owner >= 0, values[np.maximum(owner, 0)], ground).reshape(size, size)


def _edges(rng, size, config):
    return _bars(rng, size, config, thin=False)


def _lines(rng, size, config):
    return _bars(rng, size, config, thin=True)


def _spectral(rng: np.random.Generator, size: int, exponent: float) -> np.ndarray:
    """Periodic Gaussian noise with a 1/f^exponent amplitude spectrum, its 1st-99th
    percentiles mapped onto [0, 1] (clipped)."""
    f = np.sqrt(np.fft.fftfreq(size)[:, None] ** 2 + np.fft.rfftfreq(size)[None, :] ** 2)
    f[0, 0] = np.inf
    field = np.fft.irfft2(np.fft.rfft2(rng.standard_normal((size, size))) * f**-exponent, s=(size, size))
    low, high = np.percentile(field, [1.0, 99.0])
    return np.clip((field - low) / max(high - low, 1e-12), 0.0, 1.0)


def _spectral_field(rng: np.random.Generator, size: int, exponent: float) -> np.ndarray:
    """Periodic Gaussian noise with a 1/f^exponent amplitude spectrum, zero mean, unit std."""
    f = np.sqrt(np.fft.fftfreq(size)[:, None] ** 2 + np.fft.rfftfreq(size)[None, :] ** 2)
    f[0, 0] = np.inf
    field = np.fft.irfft2(np.fft.rfft2(rng.standard_normal((size, size))) * f**-exponent, s=(size, size))
    return field / max(float(field.std()), 1e-12)


def _natural(rng, size, config):
    """Textured dead leaves (module docstring): leaf levels uniform in [0, 1], each leaf showing
    a shared 1/f^exponent field (unit std) at its own strength, uniform in [0, 0.35]; the 1st to
    99th percentiles mapped onto [0, 1] (clipped). At blur 0 the power spectrum falls as
    ~f^-2.3 and the horizontal gradients' kurtosis is ~8 (tests/test_simulator_factors.py)."""
    owner, n = _leaf_owner(rng, size, config)
    levels = rng.random(n + 1)
    strength = 0.35 * rng.random(n + 1)
    top = owner.reshape(size, size)  # -1 (uncovered) picks the extra entry n
    pattern = levels[top] + strength[top] * _spectral_field(rng, size, config.exponent)
    low, high = np.percentile(pattern, [1.0, 99.0])
    return np.clip((pattern - low) / max(high - low, 1e-12), 0.0, 1.0)


def _noise(rng, size, config):
    return _spectral(rng, size, config.exponent)


def _gradient(rng, size, config):
    return _spectral(rng, size, 3.0)


def _flat(rng, size, config):
    return np.full((size, size), 0.5)


def _cell(size: int, scale: float) -> int:
    """The power of two nearest to scale that divides size (>= 2 and <= size / 4)."""
    return int(np.clip(2 ** np.rint(np.log2(max(scale, 1.0))), 2, size // 4))


def _checker(rng, size, config):
    cell = _cell(size, config.scale)
    n = size // cell
    levels = rng.uniform(0.0, 1.0, (n, n))
    if rng.random() < 0.5:  # the classic two-level board
        levels = ((np.arange(n)[:, None] + np.arange(n)[None, :]) % 2).astype(float)
    return np.kron(levels, np.ones((cell, cell)))


def _glyphs(rng, size, config):
    """Rows of random 3x5 glyphs with a stroke of scale / 4 px, a one-stroke gap between
    glyphs and rows (the canvas edge may cut the last row and column: still periodic)."""
    stroke = max(1, int(round(config.scale / 4)))
    rows, cols = size // (6 * stroke), size // (4 * stroke)
    bitmaps = rng.random((rows, cols, 5, 3)) < 0.5
    bitmaps[rng.random((rows, cols)) < 0.15] = False  # spaces between words
    cell = np.zeros((rows, cols, 6, 4), bool)
    cell[:, :, :5, :3] = bitmaps
    ink = cell.transpose(0, 2, 1, 3).reshape(rows * 6, cols * 4).repeat(stroke, 0).repeat(stroke, 1)
    canvas = np.zeros((size, size), bool)
    canvas[: ink.shape[0], : ink.shape[1]] = ink
    paper, pen = (0.9, 0.1) if rng.random() < 0.7 else (0.1, 0.9)
    return np.where(canvas, pen, paper)


def _dots(rng, size, config):
    """Sparse discs (radius 0.3-0.7 scale) covering ~8 % of a plain ground."""
    radius = config.scale * rng.uniform(0.3, 0.7, 1 << 16)
    n = int(np.searchsorted(np.cumsum(np.pi * radius**2), 0.08 * size * size)) + 1
    radius = radius[:n]
    cx, cy = rng.uniform(0, size, (2, n))
    owner = _paint(size, cx, cy, np.ceil(radius).astype(np.int64), lambda ids, dx, dy: dx**2 + dy**2 <= radius[ids, None] ** 2)
    values = rng.uniform(0.6, 1.0, n)
    return np.where(owner >= 0, values[np.maximum(owner, 0)], 0.1).reshape(size, size)


def _plaid(rng, size, config):
    """Two sine gratings, period ~2 scale, wave vectors on the integer lattice (periodic)."""
    y, x = np.mgrid[0:size, 0:size] / size
    pattern = np.full((size, size), 0.5)
    for _ in range(2):
        k = size / (2.0 * config.scale)
        angle = rng.uniform(0, np.pi)
        kx, ky = np.rint(k * np.cos(angle)), np.rint(k * np.sin(angle))
        pattern += 0.25 * np.sin(2 * np.pi * (kx * x + ky * y) + rng.uniform(0, 2 * np.pi))
    return pattern


_PATTERNS = {
    "noise": _noise,
    "edges": _edges,
    "lines": _lines,
    "checker": _checker,
    "glyphs": _glyphs,
    "gradient": _gradient,
    "flat": _flat,
    "dots": _dots,
    "plaid": _plaid,
    "natural": _natural,
}


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
