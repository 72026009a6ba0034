"""Domain randomisation: a :class:`SceneConfig` drawn from ranges of scene, motion, sensor and
geometry factors (:class:`FactorRanges`).

``TRAIN_FACTORS`` is the training distribution (split ``synthetic-dr-train``); the held-out
stress variants (``STRESS_FACTORS``, split ``synthetic-stress``) each replace one group of
factors by values the training ranges never reach:

- ``texture``: textures of the ``dots`` and ``plaid`` families (training draws neither);
- ``fast``: camera motion of 16-22 px per frame and objects of 22-30 px per frame (training
  peaks: 15 and 20);
- ``noise``: background activity of 3-6 Hz per pixel (training: at most 2 Hz);
- ``size``: a 480x640 sensor (training: at most 260x346).

``TRANSFER_FACTORS`` (split ``synthetic-transfer-train``) is a training distribution meant to
carry over to recordings the project did not make: the training ranges with surfaces textured
inside (the ``natural`` family, three draws in ten), cameras slower at the low end (0.1 px per
frame), and sensor settings over the ranges reported for DAVIS346 and Prophesee Gen3/Gen4
sensors (contrast thresholds 0.12-0.5 in log units, i.e. 13-65 % contrast; per-pixel threshold
spread 5-20 % of it; background activity 0.01-1 Hz per pixel; up to 10 hot pixels).
``TRAFFIC_FACTORS`` (held-out split ``synthetic-traffic``) looks like a street seen by a fixed
DAVIS346: a still camera, 1-4 moving objects, most of them small, background activity of
0.1-1 Hz per pixel and 2-12 hot pixels: where a network must not put flow on the noise.

Speeds are peak displacements of any visible point of a layer over one frame interval
(``1 / fps``), measured on the drawn motion (:func:`peak_flow_px`) and met by rescaling it,
so a bound holds for the sequence as drawn, not only on average.

    config = draw_scene(seed=3, height=180, width=240, factors=TRAIN_FACTORS)
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Callable

import numpy as np

from envs.simulator.motion import AffineMotion
from envs.simulator.scene import ObjectSpec, SceneConfig, SensorConfig, _next_pow2, random_shape
from envs.simulator.textures import TextureConfig

__all__ = [
    "FactorRanges",
    "TRAIN_FACTORS",
    "STRESS_FACTORS",
    "TRANSFER_FACTORS",
    "TRAFFIC_FACTORS",
    "FACTOR_SETS",
    "RANDOMIZED_VERSION",
    "draw_scene",
    "draw_size",
    "peak_flow_px",
]

# Bump whenever a change alters a randomised sequence for a given seed (the draws here, or the
# sensor effects only these splits use): it enters their cache keys, which SIMULATOR_VERSION
# alone (kept for the first splits' caches) would not change.
RANDOMIZED_VERSION = 1

Range = tuple[float, float]


@dataclass(frozen=True)
class FactorRanges:
    """Where each factor is drawn from (uniform unless "log-uniform" is said).

    sizes: (height, width) sensor sizes, one picked uniformly.
    families: texture families for the background and the objects, one drawn uniformly (a
        family listed twice is drawn twice as often).
    contrast: a layer's log-intensity range, log-uniform (0.1 = 1.1:1, 4.5 = 90:1).
    brightness: a layer's top log intensity (0.8 is white in the frames).
    static_camera: probability of a still camera (then the background is a flat or dark
        ground with probability 0.6, and there is at least one object).
    camera_flow_px: the moving camera's peak flow per frame, log-uniform.
    rotation, zoom, shake, acceleration: probabilities of each camera motion component.
    off_image_anchor: probability that the camera rotates and zooms about a point outside the
        image (else a random point inside it).
    num_objects: object count, both ends included.
    object_flow_px: each object's peak flow per frame (its rim included when it spins),
        log-uniform.
    small_object: probability that an object is small (radius 2-8 px), else 8-35 % of the
        image's short side.
    threshold: mean contrast threshold C. threshold_spread: per-pixel sigma over C.
    on_off_ratio: log-uniform. refractory_us: the refractory period.
    noise_hz: background activity per pixel, log-uniform. hot_pixels: count, both ends
        included; hot_pixel_hz: their rate, log-uniform.
    leak_hz: leak event rate (drawn with probability 0.5, else 0).
    bandwidth_tau_us: the bright pixels' low-pass time constant, log-uniform (drawn with
        probability 0.7, else no low-pass).
    """

    # One range or probability per factor of the draw (the docstring says which are log-uniform).
    sizes: tuple[tuple[int, int], ...] = ((64, 64), (96, 128), (128, 128), (120, 160), (180, 240), (128, 256), (260, 346))
    families: tuple[str, ...] = ("dead_leaves", "noise", "edges", "lines", "checker", "glyphs", "gradient", "flat")
    contrast: Range = (0.1, 4.5)
    brightness: Range = (-1.5, 0.8)
    static_camera: float = 0.25
    camera_flow_px: Range = (0.2, 15.0)
    rotation: float = 0.5
    zoom: float = 0.4
    shake: float = 0.3
    acceleration: float = 0.4
    off_image_anchor: float = 0.5
    num_objects: tuple[int, int] = (0, 6)
    object_flow_px: Range = (0.5, 20.0)
    small_object: float = 0.35
    threshold: Range = (0.1, 0.5)
    threshold_spread: Range = (0.0, 0.2)
    on_off_ratio: Range = (0.75, 1.33)
    refractory_us: Range = (0.0, 1000.0)
    noise_hz: Range = (0.01, 2.0)
    hot_pixels: tuple[int, int] = (0, 5)
    hot_pixel_hz: Range = (5.0, 300.0)
    leak_hz: Range = (0.0, 0.5)
    bandwidth_tau_us: Range = (20.0, 2000.0)


TRAIN_FACTORS = FactorRanges()

STRESS_FACTORS: dict[str, FactorRanges] = {
    "texture": dataclasses.replace(TRAIN_FACTORS, families=("dots", "plaid")),
    "fast": dataclasses.replace(TRAIN_FACTORS, static_camera=0.5, camera_flow_px=(16.0, 22.0), object_flow_px=(22.0, 30.0)),
    "noise": dataclasses.replace(TRAIN_FACTORS, noise_hz=(3.0, 6.0)),
    "size": dataclasses.replace(TRAIN_FACTORS, sizes=((480, 640),)),
}

TRANSFER_FACTORS = dataclasses.replace(
    TRAIN_FACTORS,
    families=("natural", "natural", "natural", "dead_leaves", "noise", "edges", "lines", "checker", "glyphs", "gradient", "flat"),
    camera_flow_px=(0.1, 15.0),
    threshold=(0.12, 0.5),
    threshold_spread=(0.05, 0.2),
    noise_hz=(0.01, 1.0),
    hot_pixels=(0, 10),
)

TRAFFIC_FACTORS = dataclasses.replace(
    TRAIN_FACTORS,
    sizes=((180, 240), (260, 346)),
    families=("natural", "dead_leaves", "flat"),
    static_camera=1.0,
    num_objects=(1, 4),
    object_flow_px=(0.5, 8.0),
    small_object=0.6,
    noise_hz=(0.1, 1.0),
    hot_pixels=(2, 12),
    hot_pixel_hz=(20.0, 300.0),
)

#: every named set of factor ranges (the ``factors`` of a randomised sequence)
FACTOR_SETS: dict[str, FactorRanges] = {"train": TRAIN_FACTORS, "transfer": TRANSFER_FACTORS, "traffic": TRAFFIC_FACTORS, **STRESS_FACTORS}


def draw_size(seed: int, factors: FactorRanges) -> tuple[int, int]:
    """The (height, width) of sequence ``seed``: the first draw of its own stream."""
    rng = np.random.default_rng([int(seed), 22, 0])
    return factors.sizes[int(rng.integers(len(factors.sizes)))]


def _log_uniform(rng: np.random.Generator, bounds: Range) -> float:
    return float(np.exp(rng.uniform(np.log(bounds[0]), np.log(bounds[1]))))


def draw_scene(seed: int, factors: FactorRanges = TRAIN_FACTORS, *, duration_s: float = 1.0, fps: float = 30.0) -> SceneConfig:
    """A scene drawn from ``factors`` (deterministic in ``seed``), at the size :func:`draw_size`
    gives. duration_s, fps: the sequence the speeds are fitted over (peak flow per frame)."""
    height, width = draw_size(seed, factors)
    rng = np.random.default_rng([int(seed), 22, 1])
    centre = np.array([(width - 1) / 2.0, (height - 1) / 2.0])
    frame_s = 1.0 / fps

    static = rng.random() < factors.static_camera
    if static:
        camera = AffineMotion(anchor=(float(centre[0]), float(centre[1])), camera=True)
        ground = rng.random() < 0.6 and "flat" in factors.families
        background = _draw_texture(rng, factors, family="flat" if ground else None, dark=ground and rng.random() < 0.5)
    else:
        target = _log_uniform(rng, factors.camera_flow_px)
        camera = _fit_speed(_camera_builder(rng, factors, height, width, duration_s), target, duration_s, frame_s, (height, width))
        background = _draw_texture(rng, factors)

    low, high = factors.num_objects
    n_objects = int(rng.integers(max(low, 1 if static else 0), high + 1))
    objects = tuple(_draw_object(rng, factors, height, width, duration_s, frame_s) for _ in range(n_objects))

    c = float(rng.uniform(*factors.threshold))
    sensor = SensorConfig(
        contrast_threshold=c,
        threshold_sigma=c * float(rng.uniform(*factors.threshold_spread)),
        min_threshold=0.03,
        refractory_us=int(round(rng.uniform(*factors.refractory_us))),
        noise_rate_hz=_log_uniform(rng, factors.noise_hz),
        hot_pixels=int(rng.integers(factors.hot_pixels[0], factors.hot_pixels[1] + 1)),
        hot_pixel_rate_hz=_log_uniform(rng, factors.hot_pixel_hz),
        on_off_ratio=_log_uniform(rng, factors.on_off_ratio),
        leak_rate_hz=float(rng.uniform(*factors.leak_hz)) if rng.random() < 0.5 else 0.0,
        bandwidth_tau_us=_log_uniform(rng, factors.bandwidth_tau_us) if rng.random() < 0.7 else 0.0,
        noise_refractory=True,
    )
    return SceneConfig(int(seed), int(height), int(width), camera, objects, background, sensor)


# -- textures ------------------------------------------------------------------------------


def _draw_texture(
    rng: np.random.Generator, factors: FactorRanges, *, family: str | None = None, dark: bool = False, max_scale: float = 32.0
) -> TextureConfig:
    """One layer's texture: family, contrast, brightness and feature scale."""
    family = family or factors.families[int(rng.integers(len(factors.families)))]
    contrast = _log_uniform(rng, factors.contrast)
    top = float(rng.uniform(-4.5, -2.5)) if dark else float(rng.uniform(*factors.brightness))
    scale = min(_log_uniform(rng, (2.0, 24.0)), max_scale)
    r_min = _log_uniform(rng, (1.0, 8.0))  # dead leaves at several scales
    return TextureConfig(
        r_min=r_min,
        r_max=r_min * _log_uniform(rng, (4.0, 64.0)),
        log_min=top - contrast,
        log_max=top,
        shading=0.0 if family == "flat" else float(rng.uniform(0.0, 0.2)),
        family=family,
        scale=scale,
        orientation=float(rng.uniform(0, np.pi)),
        orientation_spread=float(rng.uniform(0.0, 0.5)),
        exponent=float(rng.uniform(0.8, 1.6)),
    )


# -- motion --------------------------------------------------------------------------------


def _camera_builder(rng: np.random.Generator, factors: FactorRanges, height: int, width: int, duration_s: float):
    """The camera's motion as a function of one speed (px/s): components and their shares
    drawn now, scaled by the speed when built."""
    centre = np.array([(width - 1) / 2.0, (height - 1) / 2.0])
    half_diag = 0.5 * float(np.hypot(height, width))
    if rng.random() < factors.off_image_anchor:  # rotate / zoom about a point off the image
        angle = rng.uniform(0, 2 * np.pi)
        anchor = centre + rng.uniform(1.2, 3.0) * half_diag * np.array([np.cos(angle), np.sin(angle)])
    else:
        anchor = centre + rng.uniform(-0.5, 0.5, 2) * np.array([width, height])
    lever = float(np.hypot(*(np.abs(anchor - centre) + np.array([width, height]) / 2.0)))  # farthest corner
    use = {
        "rotation": rng.random() < factors.rotation,
        "zoom": rng.random() < factors.zoom,
        "shake": rng.random() < factors.shake,
        "acceleration": rng.random() < factors.acceleration,
    }
    shares = rng.dirichlet([3.0, 2.0, 2.0 if use["shake"] else 1e-9, 2.0 if use["rotation"] else 1e-9, 1.5 if use["zoom"] else 1e-9])
    const, sine, shake, rot, zoom = (0.0 if s < 1e-6 else float(s) for s in shares)
    direction = rng.uniform(0, 2 * np.pi)
    unit = np.array([np.cos(direction), np.sin(direction)])
    accel_turn = rng.uniform(-1.0, 1.0) if use["acceleration"] else 0.0  # speed change over the sequence, in units of v
    freq = rng.uniform(0.3, 1.5, 2)
    shake_freq = rng.uniform(4.0, 12.0, 2)
    phases = rng.uniform(0, 2 * np.pi, 6)
    spin_split = rng.uniform(0.0, 1.0)
    rot_freq = float(rng.uniform(0.3, 1.5))
    rot_sign = rng.choice([-1.0, 1.0])
    zoom_sign = rng.choice([-1.0, 1.0])
    angle0 = float(rng.uniform(0, 2 * np.pi))

    def build(speed: float) -> AffineMotion:
        velocity = speed * const * unit
        accel = 2.0 * accel_turn * speed * max(const, 0.2) * unit / duration_s
        amp = speed * sine / (2 * np.pi * freq) / np.sqrt(2.0)
        shake_amp = speed * shake / (2 * np.pi * shake_freq) / np.sqrt(2.0)
        omega = speed * rot / lever
        # steady zoom, limited to a factor 1.65 over the sequence (texture minification)
        zoom_rate = zoom_sign * min(speed * zoom / lever, 0.5 / duration_s)
        return AffineMotion(
            anchor=(float(anchor[0]), float(anchor[1])),
            velocity=(float(velocity[0]), float(velocity[1])),
            trans_amp=(float(amp[0]), float(amp[1])),
            trans_freq=(float(freq[0]), float(freq[1])),
            trans_phase=(float(phases[0]), float(phases[1])),
            angle0=angle0,
            angular_velocity=float(rot_sign * omega * spin_split),
            rot_amp=float(omega * (1 - spin_split) / (2 * np.pi * rot_freq)),
            rot_freq=rot_freq,
            rot_phase=float(phases[2]),
            camera=True,
            acceleration=(float(accel[0]), float(accel[1])) if use["acceleration"] else (0.0, 0.0),
            shake_amp=(float(shake_amp[0]), float(shake_amp[1])) if shake else (0.0, 0.0),
            shake_freq=(float(shake_freq[0]), float(shake_freq[1])) if shake else (0.0, 0.0),
            shake_phase=(float(phases[3]), float(phases[4])) if shake else (0.0, 0.0),
            zoom_rate=float(zoom_rate),
        )

    return build


def _draw_object(rng: np.random.Generator, factors: FactorRanges, height: int, width: int, duration_s: float, frame_s: float) -> ObjectSpec:
    """An object: shape, size, texture, and a path (a Lissajous loop in view, or a straight
    crossing, possibly accelerating) with a spin, fitted to a peak flow per frame."""
    small_side = min(height, width)
    if rng.random() < factors.small_object:
        radius = float(rng.uniform(2.0, 8.0))
    else:
        radius = float(rng.uniform(0.08, 0.35) * small_side)
    shape, vertices = random_shape(rng, radius)
    texture = _draw_texture(rng, factors, max_scale=max(2.0, _next_pow2(2.6 * radius) / 4))
    target = _log_uniform(rng, factors.object_flow_px)
    extent = np.array([width, height], float)
    crossing = rng.random() < 0.4
    start = rng.uniform(0.1, 0.9, 2) * extent  # where the object is halfway through
    direction = rng.uniform(0, 2 * np.pi)
    unit = np.array([np.cos(direction), np.sin(direction)])
    amp = rng.uniform(0.1, 0.4, 2) * extent
    phases = rng.uniform(0, 2 * np.pi, 4)
    ratio = rng.uniform(0.6, 1.6)  # the Lissajous loop's y frequency over its x frequency
    spin_share = rng.uniform(0.0, 0.6) if rng.random() < 0.5 else 0.0
    spin_sign = rng.choice([-1.0, 1.0])
    accel_turn = rng.uniform(-0.8, 0.8) if rng.random() < factors.acceleration else 0.0
    zoom_share = rng.uniform(0.0, 0.3) if rng.random() < factors.zoom else 0.0
    zoom_freq = float(rng.uniform(0.3, 1.5))
    angle0 = float(rng.uniform(0, 2 * np.pi))
    t_mid = 0.5 * duration_s

    def build(speed: float) -> AffineMotion:
        path = speed * (1.0 - spin_share - zoom_share)
        spin = spin_sign * speed * spin_share / max(radius, 1.0)
        # pulsing size (log-scale sine), at most x0.86-1.16
        zoom_amp = min(0.15, speed * zoom_share / (max(radius, 1.0) * 2 * np.pi * zoom_freq))
        if crossing:  # straight line, at `start` halfway through: enters and leaves the view
            velocity = path * unit
            accel = 2.0 * accel_turn * path * unit / duration_s
            anchor = start - velocity * t_mid - 0.5 * accel * t_mid**2
            trans = dict(velocity=(float(velocity[0]), float(velocity[1])), acceleration=(float(accel[0]), float(accel[1])))
        else:  # a loop around `start`, frequencies set by the speed
            fx = path / (2 * np.pi * amp[0] * np.sqrt(1 + ratio**2))
            anchor = start
            trans = dict(trans_amp=(float(amp[0]), float(amp[1])), trans_freq=(float(fx), float(fx * ratio)),
                         trans_phase=(float(phases[0]), float(phases[1])))
        return AffineMotion(
            anchor=(float(anchor[0]), float(anchor[1])),
            angle0=angle0,
            angular_velocity=float(spin),
            zoom_amp=float(zoom_amp),
            zoom_freq=zoom_freq,
            zoom_phase=float(phases[2]),
            **trans,
        )

    local = np.array([[-radius, radius, radius, -radius], [-radius, -radius, radius, radius], [1.0, 1.0, 1.0, 1.0]])
    motion = _fit_speed(build, target, duration_s, frame_s, local)
    return ObjectSpec(shape, radius, motion, vertices, texture)


def peak_flow_px(motion: AffineMotion, points, duration_s: float, frame_s: float) -> float:
    """Largest displacement (px) over any frame interval starting on a half-frame grid in
    [0, duration_s - frame_s] of the layer's bounding points: for the camera ``points`` is the
    sensor's (height, width) (its corners), for an object its (3, 4) homogeneous local corners.
    Affine motion: the largest displacement over a convex region is at a corner."""
    if isinstance(points, tuple):
        h, w = points
        corners = np.array([[0.0, w - 1.0, 0.0, w - 1.0], [0.0, 0.0, h - 1.0, h - 1.0], [1.0, 1.0, 1.0, 1.0]])
    worst = 0.0
    for t0 in np.arange(0.0, max(duration_s - frame_s, 0.0) + 1e-9, frame_s / 2):
        p0 = corners if isinstance(points, tuple) else motion.matrix(t0) @ points
        moved = motion.transfer(t0, t0 + frame_s) @ p0
        worst = max(worst, float(np.hypot(*(moved[:2] - p0[:2])).max()))
    return worst


def _fit_speed(build: Callable[[float], AffineMotion], target_px: float, duration_s: float, frame_s: float, points) -> AffineMotion:
    """The motion build(speed) whose peak flow per frame is target_px (within 1 %, or
    at most target_px when the fit runs out of iterations)."""
    speed = target_px / frame_s
    motion = build(speed)
    for _ in range(8):
        peak = peak_flow_px(motion, points, duration_s, frame_s)
        if peak <= 0 or abs(peak / target_px - 1.0) < 0.01:
            break
        speed *= target_px / peak
        motion = build(speed)
    for _ in range(300):  # never above the bound: every component scales with the speed
        if peak_flow_px(motion, points, duration_s, frame_s) <= target_px * 1.01:
            return motion
        speed *= 0.97
        motion = build(speed)
    raise RuntimeError(f"could not fit the motion to a peak flow of {target_px:.3g} px per frame")
