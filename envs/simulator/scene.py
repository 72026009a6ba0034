"""A synthetic scene: a textured background plane moved by the camera plus textured objects.

Layers, bottom to top: layer 0 is the background (a periodic dead-leaves plane moved by the
camera's :class:`AffineMotion`, ``camera=True``); layer ``k >= 1`` is object ``k - 1`` (a disc or
convex polygon with its own dead-leaves texture and its own motion), drawn over everything
below it, so objects occlude the background and each other in list order.

Rendering inverse-maps every pixel into each layer's texture coordinates and samples the
(pre-blurred, periodic) texture bilinearly; object edges are anti-aliased with a one-pixel
alpha ramp. Intensities are natural-log intensities.

Ground truth (exact, analytic): over ``[t0, t1)`` the pixel ``p`` shows at ``t0`` the point of
its *visible layer* ``l(p)`` (the topmost layer whose alpha at ``p`` is >= 0.5), and that point
is at ``A_l(t1) A_l(t0)^-1 p`` at ``t1``; the flow is the difference. It is defined everywhere,
including points that become occluded or leave the view by ``t1``, so the valid mask is all True.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np

from envs.simulator.motion import AffineMotion
from envs.simulator.textures import PeriodicTexture, TextureConfig, make_texture

__all__ = ["SensorConfig", "ObjectSpec", "SceneConfig", "Scene"]


def random_shape(rng: np.random.Generator, radius: float) -> tuple[str, tuple]:
    """A disc (3 in 10) or a convex polygon of 3-7 vertices inscribed in the circle of ``radius``
    (sorted angles with a minimum gap); returns (shape, vertices in pixels about the centre)."""
    if rng.random() < 0.3:
        return "disc", ()
    n_vert = int(rng.integers(3, 8))
    gaps = rng.uniform(0.5, 1.5, n_vert)
    angles = np.cumsum(gaps / gaps.sum() * 2 * np.pi) + rng.uniform(0, 2 * np.pi)
    return "polygon", tuple((float(radius * np.cos(a)), float(radius * np.sin(a))) for a in angles)

@dataclass(frozen=True)
class SensorConfig:
    """The event camera (ESIM-style model, see :mod:`envs.simulator.emulator`).

    contrast_threshold: mean log-intensity change per event, C.
    threshold_sigma: per-pixel, per-polarity spread of C (normal; clipped at min_threshold).
    refractory_us: after an event a pixel stays silent this long (crossings meanwhile are lost,
        but the reference still moves on). 100 us, a typical DVS value; 0 disables it.
    noise_rate_hz: background-activity noise events per pixel per second (Poisson, random
        polarity, uniform in space and time).
    hot_pixels: number of hot pixels (fixed random pixels and polarities firing at
        hot_pixel_rate_hz each, Poisson).
    on_off_ratio: mean ON threshold over mean OFF threshold (their geometric mean stays C):
        1 is balanced; > 1 makes OFF events more frequent than ON.
    leak_rate_hz: leak events: every pixel's reference sinks by C_on * leak_rate_hz per second
        (each pixel's rate spread x0.5-1.5), so a still pixel fires ON events at about that rate.
    bandwidth_tau_us: first-order pixel low-pass: the sensed log intensity follows the true one
        with time constant tau = bandwidth_tau_us * exp(-L) for L < 0 (L the log intensity,
        bandwidth proportional to intensity, capped at 100x), tau = bandwidth_tau_us at L >= 0;
        0 disables it.
    noise_refractory: whether noise and hot-pixel events obey the refractory period too (and
        silence the pixel like any event); False keeps the first model, where they do not.
    """

    # The defaults: an ideal sensor but for the threshold spread and the refractory period.
    contrast_threshold: float = 0.25
    threshold_sigma: float = 0.03
    min_threshold: float = 0.05
    refractory_us: int = 100
    noise_rate_hz: float = 0.0
    hot_pixels: int = 0
    hot_pixel_rate_hz: float = 100.0
    on_off_ratio: float = 1.0
    leak_rate_hz: float = 0.0
    bandwidth_tau_us: float = 0.0
    noise_refractory: bool = False


@dataclass(frozen=True)
class ObjectSpec:
    """One textured object. Object coordinates: pixels at scale 1, origin at the object's centre.

    shape: "disc" (radius) or "polygon" (convex; vertices in counter-clockwise angle order,
    all within radius of the origin). motion: its :class:`AffineMotion` (camera=False).
    texture: its own texture; None: the scene's, shifted by a random brightness offset.
    """

    shape: str
    radius: float
    motion: AffineMotion
    vertices: tuple[tuple[float, float], ...] = ()
    texture: TextureConfig | None = None


def _next_pow2(n: float) -> int:
    return 1 << max(5, int(np.ceil(np.log2(max(n, 1.0)))))


@dataclass(frozen=True)
class SceneConfig:
    """Everything that defines a synthetic sequence; :class:`Scene` and the simulator are
    deterministic functions of it. Build one with :meth:`random` (from a seed) or
    :meth:`translation` (pure constant translation of the background, for checks).

    seed: seeds the textures, the per-pixel thresholds and the noise.
    height, width: sensor size in pixels.
    camera: the background plane's motion (camera=True form, anchored at the image centre).
    objects: in depth order, first = lowest.
    """

    seed: int
    height: int
    width: int
    camera: AffineMotion
    objects: tuple[ObjectSpec, ...] = ()
    texture: TextureConfig = field(default_factory=TextureConfig)
    sensor: SensorConfig = field(default_factory=SensorConfig)

    @property
    def sensor_size(self) -> tuple[int, int]:
        return (self.height, self.width)

    # -- construction ------------------------------------------------------------------
    @classmethod
    def translation(
        cls, seed: int, height: int, width: int, velocity_px_s: tuple[float, float], *, sensor: SensorConfig | None = None
    ) -> "SceneConfig":
        """Background only, moving at a constant image velocity (vx, vy) px/s: the flow over
        any window of length dt is exactly (vx * dt, vy * dt) at every pixel."""
        centre = ((width - 1) / 2.0, (height - 1) / 2.0)
        # camera form: p = anchor + (q - T) with T = velocity * t, so the image moves by -velocity
        camera = AffineMotion(anchor=centre, velocity=(-velocity_px_s[0], -velocity_px_s[1]), camera=True)
        return cls(seed, height, width, camera, (), TextureConfig(), sensor or SensorConfig())

    @classmethod
    def random(
        cls,
        seed: int,
        height: int,
        width: int,
        *,
        speed_px_s: float | None = None,
        num_objects: int | None = None,
        rotation: bool = True,
        zoom: bool = True,
        noise: bool = True,
        contrast: tuple[float, float] | None = None,
        leaf_size: tuple[float, float] | None = None,
    ) -> "SceneConfig":
        """A random scene drawn from ``seed``.

        speed_px_s: bound on the image speed of any visible scene point (px/s), shared at
            random between camera pan (constant + sinusoidal), roll and zoom; objects get
            30-100 % of it. Approximate: zoomed-in phases (scale up to 1.28) can exceed it a
            little; in practice the peak over a sequence is 60-90 % of it, and slow phases of
            the sinusoids give smaller motions. Default: uniform 15-300 px/s
            (0.5-10 px per 30 Hz frame).
        num_objects: default uniform in 1..4.
        rotation, zoom: allow roll / zoom components (camera and objects).
        noise: background-activity noise (0-0.2 Hz/pixel) and 0-2 hot pixels.
        contrast: (low, high) natural-log units: the range of the leaves' log intensities,
            drawn log-uniformly in it (default: uniform in 2-3, i.e. 7:1 to 20:1). Fewer units,
            fewer threshold crossings per edge: the same motion with fewer events, as in
            photographs, whose edges are mostly weaker than the default leaves'.
        leaf_size: (low, high) pixels: the range of the smallest leaf radius (TextureConfig.r_min),
            drawn log-uniformly in it (default: uniform in 1.5-3). Larger leaves, fewer edges: most
            of the frame is flat and silent, the events lie on few long edges (as in photographs,
            where at a given speed far fewer pixels fire than on the default leaves), and a local
            view sees an edge's normal motion only (the aperture problem).
        """
        if contrast is not None and not (len(contrast) == 2 and 0 < contrast[0] <= contrast[1]):
            raise ValueError(f"contrast must be (low, high) log units with 0 < low <= high, got {contrast!r}")
        if leaf_size is not None and not (len(leaf_size) == 2 and 0 < leaf_size[0] <= leaf_size[1]):
            raise ValueError(f"leaf_size must be (low, high) pixels with 0 < low <= high, got {leaf_size!r}")
        rng = np.random.default_rng([int(seed), 0])
        speed = float(speed_px_s) if speed_px_s is not None else 30.0 * rng.uniform(0.5, 10.0)
        centre = np.array([(width - 1) / 2.0, (height - 1) / 2.0])
        half_diag = 0.5 * float(np.hypot(height, width))
        camera = _random_motion(rng, speed, half_diag, centre, camera=True, rotation=rotation, zoom=zoom)

        n_obj = int(rng.integers(1, 5)) if num_objects is None else int(num_objects)
        objects = []
        small = min(height, width)
        for _ in range(n_obj):
            radius = float(rng.uniform(0.12, 0.28) * small)
            shape, vertices = random_shape(rng, radius)
            anchor = centre + rng.uniform(-0.15, 0.15, 2) * np.array([width, height])
            motion = _random_motion(
                rng, speed * rng.uniform(0.3, 1.0), radius * 1.3, anchor, camera=False, rotation=rotation, zoom=zoom,
                extent=np.array([width, height]),
            )
            objects.append(ObjectSpec(shape, radius, motion, vertices))

        c = float(rng.uniform(0.2, 0.3))
        sensor = SensorConfig(
            contrast_threshold=c,
            threshold_sigma=0.03,
            noise_rate_hz=float(rng.uniform(0.0, 0.2)) if noise else 0.0,
            hot_pixels=int(rng.integers(0, 3)) if noise else 0,
            hot_pixel_rate_hz=float(rng.uniform(50.0, 200.0)),
        )
        if leaf_size is None:
            r_min = float(rng.uniform(1.5, 3.0))
        else:  # one draw either way, as for the contrast
            r_min = float(np.exp(rng.uniform(np.log(leaf_size[0]), np.log(leaf_size[1]))))
        if contrast is None:
            log_range = float(rng.uniform(2.0, 3.0))
        else:  # one draw either way: the rest of the scene is the default's
            log_range = float(np.exp(rng.uniform(np.log(contrast[0]), np.log(contrast[1]))))
        texture = TextureConfig(r_min=r_min, log_min=-log_range)
        return cls(int(seed), int(height), int(width), camera, tuple(objects), texture, sensor)

    # -- (de)serialisation ---------------------------------------------------------------
    def to_dict(self) -> dict:
        """A JSON-able dict (tuples become lists); :meth:`from_dict` inverts it. Fields added
        after the first splits were cached are left out while at their defaults, so an older
        config serialises (and hashes into its cache key) exactly as before."""
        return _as_dict(self)

    @classmethod
    def from_dict(cls, d: dict) -> "SceneConfig":
        objects = tuple(
            ObjectSpec(
                o["shape"], float(o["radius"]), AffineMotion.from_dict(o["motion"]), tuple(tuple(v) for v in o["vertices"]),
                TextureConfig(**o["texture"]) if o.get("texture") is not None else None,
            )
            for o in d["objects"]
        )
        return cls(
            int(d["seed"]), int(d["height"]), int(d["width"]), AffineMotion.from_dict(d["camera"]), objects,
            TextureConfig(**d["texture"]), SensorConfig(**d["sensor"]),
        )


# per class, the fields added after SIMULATOR_VERSION 2's splits were cached (see to_dict)
_ADDED_FIELDS = {
    AffineMotion: {"acceleration", "shake_amp", "shake_freq", "shake_phase", "zoom_rate"},
    TextureConfig: {"family", "scale", "orientation", "orientation_spread", "exponent"},
    SensorConfig: {"on_off_ratio", "leak_rate_hz", "bandwidth_tau_us", "noise_refractory"},
    ObjectSpec: {"texture"},
}


def _as_dict(value):
    """dataclasses.asdict, less the added fields that hold their defaults."""
    if dataclasses.is_dataclass(value):
        added = _ADDED_FIELDS.get(type(value), set())
        out = {}
        for f in dataclasses.fields(value):
            item = getattr(value, f.name)
            if f.name in added and item == f.default:
                continue
            out[f.name] = _as_dict(item)
        return out
    if isinstance(value, (tuple, list)):
        return type(value)(_as_dict(v) for v in value)
    return value


def _random_motion(
    rng: np.random.Generator,
    speed: float,
    lever: float,
    anchor: np.ndarray,
    *,
    camera: bool,
    rotation: bool,
    zoom: bool,
    extent: np.ndarray | None = None,
) -> AffineMotion:
    """Split a speed bound (px/s) between translation, rotation and zoom.

    lever: the largest distance (px) from the rotation/zoom centre at which speed counts
    (half the image diagonal for the camera, the object's radius for an object), so an angular
    rate w adds at most w * lever px/s. Camera: constant + sinusoidal pan. Object: a Lissajous
    path around its anchor (stays in view), amplitude 10-30 % of the image extent.
    """
    weights = rng.dirichlet([3.0, 2.0, 1.5 if rotation else 1e-9, 1.0 if zoom else 1e-9])
    w_const, w_sin, w_rot, w_zoom = weights * speed
    if not rotation:
        w_rot = 0.0
    if not zoom:
        w_zoom = 0.0
    phases = rng.uniform(0, 2 * np.pi, 5)
    if camera:
        direction = rng.uniform(0, 2 * np.pi)
        velocity = (float(w_const * np.cos(direction)), float(w_const * np.sin(direction)))
        freq = rng.uniform(0.3, 1.5, 2)
        amp = w_sin / (2 * np.pi * freq) / np.sqrt(2.0)
    else:
        velocity = (0.0, 0.0)
        amp = rng.uniform(0.1, 0.3, 2) * extent
        # the whole translation share goes to the Lissajous path (a constant drift would leave the view)
        freq = (w_const + w_sin) / (2 * np.pi * amp) / np.sqrt(2.0)
    # rotation: half constant spin, half oscillation (peak rate = w_rot / lever)
    omega = w_rot / lever
    split = rng.uniform(0.0, 1.0)
    rot_freq = float(rng.uniform(0.3, 1.5))
    # zoom: log-scale oscillation, peak rate 2 pi f a (capped at |a| = 0.25: scale 0.78-1.28)
    zoom_freq = float(rng.uniform(0.3, 1.5))
    zoom_amp = min(0.25, w_zoom / lever / (2 * np.pi * zoom_freq))
    return AffineMotion(
        anchor=(float(anchor[0]), float(anchor[1])),
        velocity=velocity,
        trans_amp=(float(amp[0]), float(amp[1])),
        trans_freq=(float(freq[0]), float(freq[1])),
        trans_phase=(float(phases[0]), float(phases[1])),
        angle0=float(rng.uniform(0, 2 * np.pi)),
        angular_velocity=float(omega * split * rng.choice([-1.0, 1.0])),
        rot_amp=float(omega * (1 - split) / (2 * np.pi * rot_freq)),
        rot_freq=rot_freq,
        rot_phase=float(phases[2]),
        scale0=1.0,
        zoom_amp=float(zoom_amp),
        zoom_freq=zoom_freq,
        zoom_phase=float(phases[3]),
        camera=camera,
    )


class Scene:
    """Renders a :class:`SceneConfig` and computes its exact flow. Times are in seconds.

    Textures are generated lazily (first render), so the ground-truth flow, which needs only
    the geometry, is cheap to get from a config.
    """

    def __init__(self, config: SceneConfig) -> None:
        self.config = config
        h, w = config.height, config.width
        self.height, self.width = h, w
        self._x = np.arange(w, dtype=np.float64)[None, :].repeat(h, 0)
        self._y = np.arange(h, dtype=np.float64)[:, None].repeat(w, 1)
        self._x32 = self._x.astype(np.float32)
        self._y32 = self._y.astype(np.float32)
        self.motions = [config.camera] + [o.motion for o in config.objects]
        self._textures: list[np.ndarray] | None = None
        self._background: tuple[np.ndarray, np.ndarray] | None = None  # (camera inverse, its render)
        self._polygons = []
        for obj in config.objects:
            if obj.shape == "disc":
                self._polygons.append(None)
            elif obj.shape == "polygon":
                v = np.asarray(obj.vertices, np.float64)
                edges = np.roll(v, -1, axis=0) - v
                normals = np.stack([edges[:, 1], -edges[:, 0]], 1)
                normals /= np.linalg.norm(normals, axis=1, keepdims=True)
                offsets = (normals * v).sum(1)
                flip = offsets < 0  # make every normal point away from the origin (outward)
                normals[flip] *= -1
                offsets[flip] *= -1
                self._polygons.append((normals.astype(np.float32), offsets.astype(np.float32)))
            else:
                raise ValueError(f"object shape must be 'disc' or 'polygon', got {obj.shape!r}")

    @property
    def num_layers(self) -> int:
        return len(self.motions)

    # -- textures ----------------------------------------------------------------------
    @property
    def textures(self) -> list[PeriodicTexture]:
        """Per layer: its periodic log-intensity texture (generated on first use)."""
        if self._textures is None:
            cfg = self.config
            big = _next_pow2(3.0 * max(cfg.height, cfg.width))  # >= view / min zoom, no visible tiling
            textures = [make_texture(np.random.default_rng([cfg.seed, 1, 0]), big, cfg.texture)]
            for k, obj in enumerate(cfg.objects, start=1):
                rng = np.random.default_rng([cfg.seed, 1, k])
                if obj.texture is not None:
                    textures.append(make_texture(rng, _next_pow2(2.6 * obj.radius), obj.texture))
                    continue
                # each object its own brightness range, so it stands out from what it covers
                shift = rng.uniform(-0.5, 0.5)
                tex_cfg = dataclasses.replace(cfg.texture, log_min=cfg.texture.log_min + shift, log_max=cfg.texture.log_max + shift)
                textures.append(make_texture(rng, _next_pow2(2.6 * obj.radius), tex_cfg))
            self._textures = [PeriodicTexture(tex) for tex in textures]
        return self._textures

    # -- geometry ------------------------------------------------------------------------
    def _object_region(self, k: int, t: float):
        """Object k (0-based) at time t: (rows slice, cols slice, u, v, alpha) over the image
        box that contains it, u/v its object coordinates (float32), alpha in [0, 1] its
        coverage with a one-pixel ramp; None when it is out of view."""
        obj = self.config.objects[k]
        motion = obj.motion
        a = motion.matrix(t)
        r = obj.radius + 2.0
        corners = a[:2, :2] @ np.array([[-r, r, r, -r], [-r, -r, r, r]]) + a[:2, 2:3]
        x0 = max(0, int(np.floor(corners[0].min())))
        x1 = min(self.width, int(np.ceil(corners[0].max())) + 1)
        y0 = max(0, int(np.floor(corners[1].min())))
        y1 = min(self.height, int(np.ceil(corners[1].max())) + 1)
        if x1 <= x0 or y1 <= y0:
            return None
        rows, cols = slice(y0, y1), slice(x0, x1)
        inv = motion.inverse(t).astype(np.float32)
        x, y = self._x32[rows, cols], self._y32[rows, cols]
        u = inv[0, 0] * x + inv[0, 1] * y + inv[0, 2]
        v = inv[1, 0] * x + inv[1, 1] * y + inv[1, 2]
        scale = np.float32(np.sqrt(a[0, 0] ** 2 + a[1, 0] ** 2))
        poly = self._polygons[k]
        if poly is None:
            dist = np.sqrt(u * u + v * v) - np.float32(obj.radius)
        else:  # convex polygon: max over edges of the signed distance to each edge line
            normals, offsets = poly
            dist = normals[0, 0] * u + normals[0, 1] * v - offsets[0]
            for (nx, ny), off in zip(normals[1:], offsets[1:]):
                np.maximum(dist, nx * u + ny * v - off, out=dist)
        alpha = np.clip(np.float32(0.5) - dist * scale, 0.0, 1.0)
        return rows, cols, u, v, alpha

    def visible_layers(self, t: float) -> np.ndarray:
        """(H, W) int8: index of the topmost layer with alpha >= 0.5 at each pixel (0 = background)."""
        ids = np.zeros((self.height, self.width), np.int8)
        for k in range(len(self.config.objects)):
            region = self._object_region(k, t)
            if region is not None:
                rows, cols, _, _, alpha = region
                ids[rows, cols][alpha >= 0.5] = k + 1
        return ids

    def render(self, t: float) -> np.ndarray:
        """(H, W) float32 log intensity at time t (seconds)."""
        textures = self.textures
        inv = self.config.camera.inverse(t)
        if self._background is not None and np.array_equal(inv, self._background[0]):
            image = self._background[1].copy()  # a still camera: the same background as last time
        else:
            size = textures[0].size
            # the plane's origin sits at the texture's centre; the offset is reduced modulo the
            # period first so float32 coordinates stay small (and precise) however far the camera pans
            lin = inv[:2, :2].astype(np.float32)
            off = np.mod(inv[:2, 2] + size / 2.0, size).astype(np.float32)
            u = lin[0, 0] * self._x32 + lin[0, 1] * self._y32 + off[0]
            v = lin[1, 0] * self._x32 + lin[1, 1] * self._y32 + off[1]
            image = textures[0].sample(u, v)
            self._background = (inv, image.copy())
        for k in range(len(self.config.objects)):
            region = self._object_region(k, t)
            if region is None:
                continue
            rows, cols, u, v, alpha = region
            half = np.float32(textures[k + 1].size / 2.0)
            values = textures[k + 1].sample(u + half, v + half)
            patch = image[rows, cols]  # a view: blends in place
            patch += alpha * (values - patch)
        return image

    def flow(self, t0: float, t1: float) -> np.ndarray:
        """Exact forward flow over [t0, t1): (2, H, W) float32 pixels (module docstring)."""
        ids = self.visible_layers(t0)
        flow = np.empty((2, self.height, self.width), np.float64)
        for layer, motion in enumerate(self.motions):
            m = motion.transfer(t0, t1)
            if layer == 0:
                sel = (slice(None), slice(None))
                x, y = self._x, self._y
            else:
                mask = ids == layer
                if not mask.any():
                    continue
                sel = np.nonzero(mask)
                x, y = self._x[sel], self._y[sel]
            flow[0][sel] = (m[0, 0] - 1.0) * x + m[0, 1] * y + m[0, 2]
            flow[1][sel] = m[1, 0] * x + (m[1, 1] - 1.0) * y + m[1, 2]
        return flow.astype(np.float32)

    def max_displacement(self, t0: float, t1: float) -> float:
        """Upper bound (px) on how far any visible scene point moves between t0 and t1
        (straight-line): the motion field of an affine layer is affine, so its largest norm
        over a convex region is at a corner: the image corners for the background, the
        object's bounding square for an object."""
        h, w = self.height, self.width
        corners = np.array([[0.0, w - 1.0, 0.0, w - 1.0], [0.0, 0.0, h - 1.0, h - 1.0], [1.0, 1.0, 1.0, 1.0]])
        worst = 0.0
        for layer, motion in enumerate(self.motions):
            if layer == 0:
                points = corners
            else:
                r = self.config.objects[layer - 1].radius
                local = np.array([[-r, r, r, -r], [-r, -r, r, r], [1.0, 1.0, 1.0, 1.0]])
                points = motion.matrix(t0) @ local
            moved = motion.transfer(t0, t1) @ points
            worst = max(worst, float(np.hypot(*(moved[:2] - points[:2])).max()))
        return worst
