"""Pictures of event windows and flow fields (uint8 RGB, H x W x 3).

- :func:`flow_to_rgb`: the standard optical-flow colour wheel (Baker et al., Middlebury):
  hue = direction, saturation = magnitude relative to ``max_magnitude``; zero flow is white.
- :func:`count_image_to_rgb`: ON events red, OFF events blue, on white.
- :func:`flow_legend`: the colour wheel itself, a disc whose rim is ``max_magnitude``.
- :func:`flow_arrows`: sparse arrows along the flow drawn over a picture.
- :func:`panel`: labelled tiles side by side with a caption underneath (one picture per window).
- :func:`save_png`: writes a picture atomically (Pillow, the ``plots``/``test`` extra).
- :func:`save_animation`: frames to an animated GIF (Pillow), or MP4 where ``imageio`` with an
  ffmpeg codec is installed; written atomically.
"""

from __future__ import annotations

import math
import os
from pathlib import Path
from typing import Iterable

import numpy as np

__all__ = ["color_wheel", "flow_to_rgb", "flow_legend", "flow_arrows", "count_image_to_rgb", "panel", "save_png",
           "save_animation", "animation_path"]

# Hue segments of the Middlebury wheel: red-yellow, yellow-green, green-cyan, cyan-blue,
# blue-magenta, magenta-red, with these many steps each.
_SEGMENTS = (15, 6, 4, 11, 13, 6)


def color_wheel() -> np.ndarray:
    """(55, 3) float64 RGB in [0, 255]: the wheel's colours in order of angle."""
    ramps = []
    # (channel that is full, channel that ramps, ramp up or down) for each segment
    plan = ((0, 1, +1), (1, 0, -1), (1, 2, +1), (2, 1, -1), (2, 0, +1), (0, 2, -1))
    for steps, (full, moving, direction) in zip(_SEGMENTS, plan):
        seg = np.zeros((steps, 3))
        seg[:, full] = 255
        ramp = np.floor(255 * np.arange(steps) / steps)
        seg[:, moving] = ramp if direction > 0 else 255 - ramp
        ramps.append(seg)
    return np.concatenate(ramps)


def flow_to_rgb(flow: np.ndarray, max_magnitude: float | None = None) -> np.ndarray:
    """Colour-code a flow field.

    flow: (2, H, W) pixels (x then y). max_magnitude: the magnitude shown fully saturated
    (default: the field's largest finite magnitude). Returns (H, W, 3) uint8.
    """
    flow = np.asarray(flow, np.float64)
    if flow.ndim != 3 or flow.shape[0] != 2:
        raise ValueError(f"flow must be (2, H, W), got {flow.shape}")
    u, v = np.nan_to_num(flow[0]), np.nan_to_num(flow[1])
    magnitude = np.hypot(u, v)
    if max_magnitude is None:
        max_magnitude = float(magnitude.max())
    scale = max(float(max_magnitude), 1e-9)
    wheel = color_wheel()
    n = len(wheel)
    angle = np.arctan2(-v, -u) / np.pi  # in [-1, 1]
    position = (angle + 1) / 2 * (n - 1)
    k0 = np.floor(position).astype(int)
    k1 = (k0 + 1) % n
    frac = (position - k0)[..., None]
    colour = (1 - frac) * wheel[k0] + frac * wheel[k1]  # (H, W, 3) in [0, 255]
    radius = np.clip(magnitude / scale, 0, 1)[..., None]
    rgb = 255 - radius * (255 - colour)
    return np.clip(np.rint(rgb), 0, 255).astype(np.uint8)


def count_image_to_rgb(count_image: np.ndarray) -> np.ndarray:
    """(2, H, W) counts [ON, OFF] -> (H, W, 3) uint8: ON red, OFF blue, no events white."""
    count_image = np.asarray(count_image, np.float64)
    if count_image.ndim != 3 or count_image.shape[0] != 2:
        raise ValueError(f"count image must be (2, H, W), got {count_image.shape}")
    scale = max(np.percentile(count_image[count_image > 0], 99) if (count_image > 0).any() else 1.0, 1.0)
    on, off = np.clip(count_image / scale, 0, 1)
    rgb = np.stack([1 - off, 1 - on - off, 1 - on], axis=-1)
    return (np.clip(rgb, 0, 1) * 255).astype(np.uint8)


def save_png(path: str | os.PathLike, rgb: np.ndarray) -> Path:
    """Write an (H, W, 3) uint8 picture as PNG through a temporary file."""
    from PIL import Image

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f"{path.name}.tmp-{os.getpid()}")
    try:
        Image.fromarray(np.ascontiguousarray(rgb)).save(tmp, format="PNG")
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
    return path


def flow_legend(size: int = 64) -> np.ndarray:
    """(size, size, 3) uint8: the colour wheel as a disc; a pixel's colour is that of a flow
    pointing from the centre to it, the rim being the magnitude shown fully saturated."""
    r = (np.arange(size) - (size - 1) / 2) / ((size - 1) / 2)
    u, v = np.meshgrid(r, r)
    rgb = flow_to_rgb(np.stack([u, v]), max_magnitude=1.0)
    rgb[np.hypot(u, v) > 1] = 255
    return rgb


def flow_arrows(rgb: np.ndarray, flow: np.ndarray, mask: np.ndarray | None = None, spacing: int = 12,
                colour: tuple[int, int, int] = (0, 0, 0)) -> np.ndarray:
    """``rgb`` with an arrow along the flow from every ``spacing``-th pixel (where ``mask`` holds),
    scaled so that the longest is ``spacing`` pixels long; zero flow draws nothing.

    rgb: (H, W, 3) uint8; flow: (2, H, W) pixels (x then y); mask: (H, W) bool or None (every
    pixel). Returns a new (H, W, 3) uint8 picture."""
    from PIL import Image, ImageDraw

    h, w = rgb.shape[:2]
    ys, xs = np.mgrid[spacing // 2 : h : spacing, spacing // 2 : w : spacing]
    ys, xs = ys.ravel(), xs.ravel()
    if mask is not None:
        keep = np.asarray(mask, bool)[ys, xs]
        ys, xs = ys[keep], xs[keep]
    u, v = np.nan_to_num(flow[0][ys, xs]), np.nan_to_num(flow[1][ys, xs])
    longest = float(np.hypot(u, v).max()) if len(u) else 0.0
    canvas = Image.fromarray(np.ascontiguousarray(rgb[..., :3]))
    if longest <= 1e-9:
        return np.asarray(canvas, np.uint8)
    draw = ImageDraw.Draw(canvas)
    scale = spacing / longest
    for x0, y0, du, dv in zip(xs.tolist(), ys.tolist(), (u * scale).tolist(), (v * scale).tolist()):
        x1, y1 = x0 + du, y0 + dv
        draw.line([(x0, y0), (x1, y1)], fill=colour)
        length = math.hypot(du, dv)
        if length >= 3:  # the head: two strokes back from the tip at +-30 degrees
            bx, by = -du / length * 3, -dv / length * 3
            for c, s_ in ((0.866, 0.5), (0.866, -0.5)):
                draw.line([(x1, y1), (x1 + c * bx - s_ * by, y1 + s_ * bx + c * by)], fill=colour)
    return np.asarray(canvas, np.uint8)


def _text_height() -> int:
    return 12


def panel(tiles: list[tuple[str, np.ndarray]], caption: str = "", gap: int = 4, min_width: int = 120) -> np.ndarray:
    """Tiles side by side, each with its label above it, and ``caption`` below all of them.

    tiles: (label, (h, w, 3) uint8) pairs; tiles of different heights are top-aligned on white;
    tiles narrower than ``min_width`` are enlarged by a whole factor (nearest neighbour) so
    that labels fit and pixels stay sharp. Returns (H, W, 3) uint8. Text is drawn with
    Pillow's built-in bitmap font.
    """
    from PIL import Image, ImageDraw

    factor = max(1, -(-min_width // max(t.shape[1] for _, t in tiles)))
    tiles = [(label, np.repeat(np.repeat(t, factor, 0), factor, 1)) for label, t in tiles]

    line = _text_height()
    height = max(t.shape[0] for _, t in tiles) + 2 * line + 3 * gap
    width = sum(t.shape[1] for _, t in tiles) + gap * (len(tiles) + 1)
    width = max(width, 6 * len(caption) + 2 * gap)
    canvas = Image.new("RGB", (width, height), (255, 255, 255))
    draw = ImageDraw.Draw(canvas)
    left = gap
    for label, tile in tiles:
        draw.text((left, gap // 2), label, fill=(0, 0, 0))
        canvas.paste(Image.fromarray(np.ascontiguousarray(tile)), (left, line + gap))
        left += tile.shape[1] + gap
    if caption:
        draw.text((gap, height - line - gap // 2), caption, fill=(0, 0, 0))
    return np.asarray(canvas, np.uint8)


def animation_path(path: str | os.PathLike) -> Path:
    """The file :func:`save_animation` writes for ``path``: itself, or for an ``.mp4`` without
    ``imageio`` and its ffmpeg plugin the GIF beside it (same stem). A command claims this path
    (``envs.outputs.Output``) before its work."""
    path = Path(path)
    if path.suffix.lower() == ".mp4":
        try:
            import imageio.v3  # noqa: F401
            import imageio_ffmpeg  # noqa: F401  (the codec imageio needs for MP4)
        except ImportError:
            return path.with_suffix(".gif")
    return path


def _padded(frame: np.ndarray, h: int, w: int) -> np.ndarray:
    """``frame`` (H, W, 3+) on a white (h, w) canvas, top-left aligned (cut where larger)."""
    canvas = np.full((h, w, 3), 255, np.uint8)
    fh, fw = min(h, frame.shape[0]), min(w, frame.shape[1])
    canvas[:fh, :fw] = frame[:fh, :fw, :3]
    return canvas


def _palette(samples: list):
    """One palette of 256 colours for a GIF, chosen (median cut) from ``samples`` (PIL images)."""
    from PIL import Image

    sheet = Image.new("RGB", (max(i.width for i in samples), sum(i.height for i in samples)), (255, 255, 255))
    top = 0
    for image in samples:
        sheet.paste(image, (0, top))
        top += image.height
    return sheet.quantize(colors=256, method=Image.Quantize.MEDIANCUT)


def save_animation(path: str | os.PathLike, frames: Iterable[np.ndarray], fps: float = 10.0) -> Path:
    """Write (H, W, 3) uint8 frames as an animation through a temporary file.

    ``.gif``: Pillow (always available with the ``test``/``plots`` extras), every frame dithered
    (Floyd-Steinberg) onto one shared palette of 256 colours, so that a colour wheel's smooth hues
    do not break into bands nor a colour flicker from frame to frame (a palette per frame does
    both); ``.png`` / ``.apng``: an animated PNG (lossless, larger). ``.mp4``: through ``imageio``
    with its ffmpeg plugin; when that is not installed the frames go to a GIF beside it instead
    (same stem) and that path is returned. A list of frames of different sizes is padded with
    white to the largest, its palette chosen from 16 frames spread over it; frames given as an
    iterator (a GIF then holds one frame at a time as RGB) take the first frame's size and palette.
    """
    from PIL import Image

    lazy = not isinstance(frames, (list, tuple))
    frames = iter(frames) if lazy else list(frames)
    first = next(frames, None) if lazy else (frames[0] if frames else None)
    if first is None:
        raise ValueError(f"{path}: no frames to write")
    if lazy:
        h, w = first.shape[:2]
        rest = (_padded(f, h, w) for f in frames)
    else:
        h, w = max(f.shape[0] for f in frames), max(f.shape[1] for f in frames)
        rest = (_padded(f, h, w) for f in frames[1:])
    path = animation_path(Path(path))
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f"{path.stem}.tmp-{os.getpid()}{path.suffix}")
    duration = int(round(1000 / fps))
    try:
        head = _padded(first, h, w)
        if path.suffix.lower() == ".mp4":
            import imageio.v3 as iio

            even = [f[: h - h % 2, : w - w % 2] for f in (head, *rest)]  # even sizes for yuv420p
            iio.imwrite(tmp, np.stack(even), fps=fps, codec="libx264")
        elif path.suffix.lower() in (".png", ".apng"):  # animated PNG: lossless, no palette
            images = [Image.fromarray(f) for f in (head, *rest)]
            images[0].save(tmp, format="PNG", save_all=True, append_images=images[1:], duration=duration, loop=0)
        else:
            samples = [head] if lazy else [_padded(f, h, w) for f in frames[:: max(1, len(frames) // 16)]]
            palette = _palette([Image.fromarray(f) for f in samples])
            dither = lambda f: Image.fromarray(f).quantize(palette=palette, dither=Image.Dither.FLOYDSTEINBERG)  # noqa: E731
            images = [dither(head), *(dither(f) for f in rest)]
            images[0].save(tmp, format="GIF", save_all=True, append_images=images[1:], duration=duration, loop=0)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
    return path
