"""The domain-randomised factors of the simulator (envs.simulator.randomize, the new sensor
effects, motions and textures) and the splits built from them (synthetic-dr-train,
synthetic-stress).

Each sensor effect is checked against an analytic reference (Poisson rates, dead time, the
first-order step response, a ramp's crossing times); the new motions' ground truth against a
closed form and the independent event and frame checks of tests/test_simulator.py.
"""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from envs.simulator import AffineMotion, EventEmulator, Scene, SceneConfig, SensorConfig, TextureConfig, simulate
from envs.simulator.export import OUTPUT_FORMATS, write_sequence
from envs.simulator.randomize import STRESS_FACTORS, TRAFFIC_FACTORS, TRAIN_FACTORS, TRANSFER_FACTORS, peak_flow_px
from envs.simulator.textures import make_texture
from envs.synthetic import (
    SyntheticH5Reader,
    clear_cache,
    generate_split,
    get_spec,
    list_sequences,
    load_sequence,
    start_generation,
)
from tests.test_simulator import _bilinear, _iwe_variance

FLAT = TextureConfig(family="flat", log_min=-1.0, log_max=-1.0, shading=0.0)


def _still_blank(height: int, width: int, sensor: SensorConfig, seed: int = 0) -> SceneConfig:
    """A still camera on a uniform wall: every event is noise, a hot pixel or a leak."""
    centre = ((width - 1) / 2.0, (height - 1) / 2.0)
    return SceneConfig(seed, height, width, AffineMotion(anchor=centre, camera=True), (), FLAT, sensor)


def _pixel_gaps(x: np.ndarray, y: np.ndarray, t: np.ndarray, width: int) -> np.ndarray:
    """Time between consecutive events of the same pixel (us), all pixels together."""
    pixel = y.astype(np.int64) * width + x
    order = np.lexsort((t, pixel))
    same = pixel[order][1:] == pixel[order][:-1]
    return np.diff(t[order])[same]


# --- sensor effects --------------------------------------------------------------------------


@pytest.mark.parametrize("rate_hz", [0.05, 2.0])
def test_background_noise_rate_on_a_blank_scene(rate_hz):
    sensor = SensorConfig(noise_rate_hz=rate_hz, refractory_us=100, noise_refractory=True, bandwidth_tau_us=300.0)
    seq = simulate(_still_blank(96, 128, sensor), duration_s=4.0)
    expected = rate_hz * 96 * 128 * 4.0
    assert abs(len(seq.events) / expected - 1.0) < 0.10
    assert abs((seq.events.p > 0).mean() - 0.5) < 0.05  # random polarity


def test_hot_pixels_fire_at_their_rate_less_the_dead_time():
    rate, refractory = 400.0, 1000
    for noise_refractory, expected in ((False, rate), (True, rate / (1.0 + rate * refractory * 1e-6))):
        sensor = SensorConfig(hot_pixels=3, hot_pixel_rate_hz=rate, refractory_us=refractory, noise_refractory=noise_refractory)
        seq = simulate(_still_blank(32, 32, sensor, seed=4), duration_s=4.0)
        pixels, counts = np.unique(seq.events.y.astype(int) * 32 + seq.events.x, return_counts=True)
        assert len(pixels) == 3  # nothing else fires on a blank wall without noise
        # a non-paralysable dead time after each emitted event: rate r -> r / (1 + r R)
        np.testing.assert_allclose(counts / 4.0, expected, rtol=0.08)


def test_no_two_events_of_a_pixel_within_the_refractory_period():
    # fast, high-contrast edges and a low threshold: many crossings per pixel within 700 us
    sensor = SensorConfig(contrast_threshold=0.1, threshold_sigma=0.01, refractory_us=700, noise_rate_hz=2.0, hot_pixels=4,
                          hot_pixel_rate_hz=300.0, leak_rate_hz=0.5, bandwidth_tau_us=100.0, on_off_ratio=1.2, noise_refractory=True)
    base = dataclasses.replace(SceneConfig.translation(11, 64, 96, (420.0, 150.0)), texture=TextureConfig(family="edges", log_min=-3.0, log_max=0.5))
    seq = simulate(dataclasses.replace(base, sensor=sensor), duration_s=0.5)
    ev = seq.events
    assert len(ev) > 20_000
    assert _pixel_gaps(ev.x, ev.y, ev.t, 96).min() >= 700
    # the check bites: without any refractory period the same scene has closer events
    free = simulate(dataclasses.replace(base, sensor=dataclasses.replace(sensor, refractory_us=0)), duration_s=0.5)
    assert (_pixel_gaps(free.events.x, free.events.y, free.events.t, 96) < 700).sum() > 1000


def test_bandwidth_lag_on_a_brightness_step_matches_the_time_constant():
    tau0, c, jump = 400.0, 0.22, 1.0
    start = np.array([[0.0, -3.0]], np.float32)  # a bright pixel and a dark one
    end = start + jump
    sensor = SensorConfig(contrast_threshold=c, threshold_sigma=0.0, refractory_us=0, bandwidth_tau_us=tau0)
    emulator = EventEmulator(start, sensor, np.random.default_rng(0))
    parts = [emulator.step(start, end, 0, 1)]  # the step, within 1 us
    for t in range(1, 40_000, 10):
        parts.append(emulator.step(end, end, t, t + 10))
    x, t = (np.concatenate([part[i] for part in parts]) for i in (0, 2))
    # first-order low-pass: F(t) = L_b - jump exp(-t / tau) crosses the j-th threshold at
    # t_j = -tau ln(1 - j C / jump); tau = tau0 for the bright pixel, tau0 e^2 at L = -2
    crossings = -np.log(1.0 - c * np.arange(1, 5) / jump)
    for pixel, tau in ((0, tau0), (1, tau0 * np.exp(2.0))):
        np.testing.assert_allclose(t[x == pixel], tau * crossings, rtol=0.01, atol=2.0)


def test_threshold_spread_and_on_off_imbalance_as_set():
    c, sigma, ratio = 0.3, 0.04, 1.2
    sensor = SensorConfig(contrast_threshold=c, threshold_sigma=sigma, on_off_ratio=ratio, refractory_us=0)
    h, w = 100, 120
    start = np.zeros((h, w), np.float32)
    # a ramp of slope +-k: each pixel's first event comes at its own ON / OFF threshold / k
    k, step_us = 1e-4, 50  # log units per us
    for sign, mean in ((1.0, c * np.sqrt(ratio)), (-1.0, c / np.sqrt(ratio))):
        emulator = EventEmulator(start, sensor, np.random.default_rng(3))
        first = np.full(h * w, -1.0)
        previous = start
        for t in range(0, 6000, step_us):
            current = np.full((h, w), sign * k * (t + step_us), np.float32)
            x, y, ts, p = emulator.step(previous, current, t, t + step_us)
            assert np.all(p == sign)
            idx = y.astype(int) * w + x
            new = first[idx] < 0
            first[idx[new]] = ts[new]
            previous = current
        assert (first >= 0).all()
        measured = k * (first + 0.5)  # the integer-us timestamps floor the crossing times
        assert abs(measured.mean() / mean - 1.0) < 0.01
        assert abs(measured.std() / sigma - 1.0) < 0.06


def test_leak_events_on_a_still_pixel():
    sensor = SensorConfig(leak_rate_hz=0.5, refractory_us=0)
    seq = simulate(_still_blank(64, 64, sensor), duration_s=4.0)
    assert (seq.events.p > 0).all()  # leak fires ON events only
    # per pixel the rate is 0.5 Hz x U(0.5, 1.5) from a random phase: 0.5 Hz on average
    assert abs(len(seq.events) / (0.5 * 64 * 64 * 4.0) - 1.0) < 0.10


# --- motions: exact ground truth ---------------------------------------------------------------


def test_rotation_about_an_off_image_point_and_zoom_match_closed_form():
    h, w = 40, 56
    anchor = np.array([-120.0, 90.0])  # off the image, left of it
    camera = AffineMotion(anchor=tuple(anchor), angular_velocity=0.6, zoom_rate=-0.3, camera=True)
    scene = Scene(SceneConfig(0, h, w, camera))
    t0, t1 = 0.2, 0.25
    flow = scene.flow(t0, t1)
    ratio, angle = np.exp(-0.3 * (t1 - t0)), 0.6 * (t1 - t0)
    ys, xs = np.mgrid[0:h, 0:w].astype(float)
    dx, dy = xs - anchor[0], ys - anchor[1]
    x1 = anchor[0] + ratio * (np.cos(angle) * dx - np.sin(angle) * dy)
    y1 = anchor[1] + ratio * (np.sin(angle) * dx + np.cos(angle) * dy)
    np.testing.assert_allclose(flow[0], x1 - xs, atol=1e-4)
    np.testing.assert_allclose(flow[1], y1 - ys, atol=1e-4)
    assert np.abs(flow).max() > 3


def test_accelerating_shaking_pan_matches_closed_form():
    h, w = 20, 30
    camera = AffineMotion(anchor=(14.5, 9.5), velocity=(30.0, -10.0), acceleration=(200.0, 50.0), shake_amp=(2.0, 1.0),
                          shake_freq=(8.0, 5.0), shake_phase=(0.2, 0.9), camera=True)
    scene = Scene(SceneConfig(0, h, w, camera))

    def pan(t):  # T(t), per axis; a camera pan by T moves the image by -T
        return np.array([30.0 * t + 100.0 * t * t + 2.0 * np.sin(2 * np.pi * 8.0 * t + 0.2),
                         -10.0 * t + 25.0 * t * t + 1.0 * np.sin(2 * np.pi * 5.0 * t + 0.9)])

    for t0, t1 in ((0.0, 0.033), (0.4, 0.5), (0.31, 0.29)):
        flow = scene.flow(t0, t1)
        expected = -(pan(t1) - pan(t0))
        np.testing.assert_allclose(flow[0], expected[0], atol=1e-4)
        np.testing.assert_allclose(flow[1], expected[1], atol=1e-4)


def _camera(kind: str, h: int, w: int) -> AffineMotion:
    centre = ((w - 1) / 2.0, (h - 1) / 2.0)
    if kind == "roll-off-image":
        return AffineMotion(anchor=(-100.0, 1.5 * h), angular_velocity=0.7, camera=True)
    if kind == "zoom":
        return AffineMotion(anchor=(0.3 * w, 0.6 * h), zoom_rate=1.5, camera=True)
    if kind == "shake-acceleration":
        return AffineMotion(anchor=centre, velocity=(40.0, -20.0), acceleration=(300.0, 200.0), shake_amp=(1.5, 1.0),
                            shake_freq=(9.0, 6.0), shake_phase=(0.3, 1.1), camera=True)
    raise ValueError(kind)


@pytest.fixture(scope="module", params=["roll-off-image", "zoom", "shake-acceleration"])
def new_motion(request):
    """A 48x64 scene under one of the new camera motions, with a spinning and a crossing object."""
    h, w = 48, 64
    spinning = AffineMotion(anchor=(20.0, 30.0), angle0=0.4, angular_velocity=6.0)
    crossing = AffineMotion(anchor=(5.0, 12.0), velocity=(120.0, 30.0), acceleration=(-100.0, 0.0))
    objects = (
        _object_spec("polygon", 10.0, spinning),
        _object_spec("disc", 6.0, crossing),
    )
    config = SceneConfig(5, h, w, _camera(request.param, h, w), objects, TextureConfig(), SensorConfig())
    return simulate(config, duration_s=0.3)


def _object_spec(shape, radius, motion):
    from envs.simulator import ObjectSpec

    vertices = tuple((radius * np.cos(a), radius * np.sin(a)) for a in np.linspace(0, 2 * np.pi, 6)[:-1]) if shape == "polygon" else ()
    return ObjectSpec(shape, radius, motion, vertices, TextureConfig(family="checker", scale=4.0, log_min=-2.0, log_max=0.5))


def test_new_motions_warping_events_with_ground_truth_sharpens_them(new_motion):
    seq = new_motion
    times = seq.frame_times
    for k in range(len(times) - 1):
        t0, t1 = int(times[k]), int(times[k + 1])
        flow, _ = seq.flow_between(t0, t1)
        assert np.abs(flow).max() > 1.0
        events = seq.events.slice_time(t0, t1)
        sharp = _iwe_variance(events, flow, t0, t1)
        assert sharp > 1.2 * _iwe_variance(events, 0 * flow, t0, t1)
        assert sharp > 1.1 * _iwe_variance(events, 2 * flow, t0, t1)


def test_new_motions_frames_agree_after_warping_by_ground_truth(new_motion):
    seq = new_motion
    h, w = seq.sensor_size
    ys, xs = np.mgrid[0:h, 0:w]
    errors, zero_errors = [], []
    for k in range(0, len(seq.frame_times) - 2, 2):
        t0, t1 = int(seq.frame_times[k]), int(seq.frame_times[k + 2])
        flow, _ = seq.flow_between(t0, t1)
        x1, y1 = xs + flow[0], ys + flow[1]
        inside = (x1 >= 1) & (x1 < w - 2) & (y1 >= 1) & (y1 < h - 2)
        ids0, ids1 = seq.visible_layers(t0), seq.visible_layers(t1)
        same = np.zeros_like(inside)
        same[inside] = ids1[np.rint(y1[inside]).astype(int), np.rint(x1[inside]).astype(int)] == ids0[inside]
        pad = np.pad(ids0, 2, mode="edge")
        interior = np.all([pad[2 + dy : 2 + dy + h, 2 + dx : 2 + dx + w] == ids0 for dy in range(-2, 3) for dx in range(-2, 3)], axis=0)
        keep = inside & same & interior
        assert keep.mean() > 0.3
        errors.append(np.abs(_bilinear(seq.frames[k + 2], x1[keep], y1[keep]) - seq.frames[k][keep]))
        zero_errors.append(np.abs(seq.frames[k + 2][keep].astype(float) - seq.frames[k][keep]))
    error, zero_error = np.concatenate(errors).mean(), np.concatenate(zero_errors).mean()
    assert error < 2.5 and error < 0.2 * zero_error


# --- textures --------------------------------------------------------------------------------


@pytest.mark.parametrize("family", ["noise", "edges", "lines", "checker", "glyphs", "gradient", "flat", "dots", "plaid", "natural"])
def test_texture_families_fill_their_range(family):
    config = TextureConfig(family=family, log_min=-2.0, log_max=0.0, shading=0.0, blur_sigma=0.0)
    texture = make_texture(np.random.default_rng(0), 128, config)
    assert texture.shape == (128, 128) and texture.dtype == np.float32
    assert texture.min() >= -2.0 - 1e-4 and texture.max() <= 1e-4
    if family == "flat":
        assert texture.std() < 1e-6
    else:
        assert texture.std() > 0.05
    with pytest.raises(ValueError, match="family"):
        TextureConfig(family="photograph")


def _power_slope(texture: np.ndarray) -> float:
    """Log-log slope of the power spectrum between 2 cycles per image and 1/4 cycle per pixel."""
    n = texture.shape[0]
    power = np.abs(np.fft.fft2(texture - texture.mean())) ** 2
    f = np.hypot(np.fft.fftfreq(n)[:, None], np.fft.fftfreq(n)[None, :])
    band = (f > 2 / n) & (f < 0.25)
    return float(np.polyfit(np.log(f[band]), np.log(power[band]), 1)[0])


def _gradient_kurtosis(texture: np.ndarray) -> float:
    g = np.diff(texture.astype(float), axis=1).ravel()
    g -= g.mean()
    return float((g**4).mean() / (g**2).mean() ** 2)


@pytest.mark.parametrize("seed", [0, 1])
def test_natural_texture_has_natural_image_statistics_and_texture_inside_leaves(seed):
    """Photographs: power spectra ~1/f^2 (slopes about -1.6 to -3), heavy-tailed gradients
    (kurtosis well above a Gaussian's 3), and texture almost everywhere. Plain dead leaves
    share the first two but are flat inside their leaves; 1/f noise shares the first only."""
    def texture(family):
        config = TextureConfig(family=family, log_min=-2.0, log_max=0.0, shading=0.0, blur_sigma=0.0)
        return make_texture(np.random.default_rng(seed), 256, config)

    natural, leaves, noise = texture("natural"), texture("dead_leaves"), texture("noise")
    assert -3.0 < _power_slope(natural) < -1.6
    assert _gradient_kurtosis(natural) > 6.0 and _gradient_kurtosis(noise) < 4.0
    textured = lambda t: float((np.abs(np.diff(t, axis=1)) > 1e-3).mean())  # noqa: E731
    assert textured(natural) > 0.6 and textured(leaves) < 0.3
    again = make_texture(np.random.default_rng(seed), 256, TextureConfig(family="natural", shading=0.0, blur_sigma=0.0,
                                                                          log_min=-2.0, log_max=0.0))
    np.testing.assert_array_equal(natural, again)


def test_a_pan_over_natural_texture_gives_events_that_follow_the_truth():
    """Events of a pan over textured leaves, warped by the exact flow, are sharper than
    unwarped or warped twice as far (the texture inside the leaves moves with them)."""
    h, w = 48, 64
    camera = AffineMotion(anchor=((w - 1) / 2.0, (h - 1) / 2.0), velocity=(90.0, 40.0), camera=True)
    texture = TextureConfig(family="natural", r_min=4.0, r_max=32.0, log_min=-2.0, log_max=0.0)
    seq = simulate(SceneConfig(3, h, w, camera, (), texture, SensorConfig()), duration_s=0.2)
    times = seq.frame_times
    for k in range(len(times) - 1):
        t0, t1 = int(times[k]), int(times[k + 1])
        flow, _ = seq.flow_between(t0, t1)
        events = seq.events.slice_time(t0, t1)
        assert len(events.t) > 0.1 * h * w
        sharp = _iwe_variance(events, flow, t0, t1)
        assert sharp > 1.2 * _iwe_variance(events, 0 * flow, t0, t1)
        assert sharp > 1.1 * _iwe_variance(events, 2 * flow, t0, t1)


# --- the splits ------------------------------------------------------------------------------


def test_dr_train_catalogue_and_any_size():
    specs = list_sequences("synthetic-dr-train")
    assert len(specs) == 256 and len({s.name for s in specs}) == 256
    sizes = {(s.height, s.width) for s in specs}
    assert min(h for h, _ in sizes) >= 64 and min(w for _, w in sizes) >= 64  # fits a 64x64 crop
    assert (64, 64) in sizes and (260, 346) in sizes and any(h != w for h, w in sizes)
    more = list_sequences("synthetic-dr-train:300")
    assert len(more) == 300 and more[:256] == specs  # a larger split extends the default one
    assert get_spec("synthetic-dr-train:300", 299).name == "synthetic-dr-train-00299"
    with pytest.raises(ValueError, match="positive integer"):
        list_sequences("synthetic-dr-train:many")


def test_training_draws_stay_inside_their_ranges_and_stress_outside():
    frame_s = 1 / 30
    for spec in list_sequences("synthetic-dr-train")[:24]:
        config = spec.config()
        families = {config.texture.family} | {o.texture.family for o in config.objects}
        assert families <= set(TRAIN_FACTORS.families) and not families & {"dots", "plaid"}
        assert 0.01 <= config.sensor.noise_rate_hz <= 2.0 and 0.1 <= config.sensor.contrast_threshold <= 0.5
        assert 0 <= config.sensor.refractory_us <= 1000
        assert peak_flow_px(config.camera, config.sensor_size, 1.0, frame_s) <= 15.0 * 1.01
        for obj in config.objects:
            corners = np.array([[-obj.radius, obj.radius, obj.radius, -obj.radius], [-obj.radius, -obj.radius, obj.radius, obj.radius], [1.0] * 4])
            assert peak_flow_px(obj.motion, corners, 1.0, frame_s) <= 20.0 * 1.01
    stress = {spec.name: spec.config() for spec in list_sequences("synthetic-stress")}
    assert set(STRESS_FACTORS) == {name.split("-")[2] for name in stress}
    for name, config in stress.items():
        group = name.split("-")[2]
        if group == "texture":
            assert config.texture.family in ("dots", "plaid")
        elif group == "noise":
            assert config.sensor.noise_rate_hz >= 3.0
        elif group == "size":
            assert config.sensor_size == (480, 640)
        else:  # fast: the camera or an object beyond anything the training split draws
            camera = peak_flow_px(config.camera, config.sensor_size, 1.0, frame_s)
            objects = [
                peak_flow_px(o.motion, np.array([[-o.radius, o.radius, o.radius, -o.radius], [-o.radius, -o.radius, o.radius, o.radius], [1.0] * 4]), 1.0, frame_s)
                for o in config.objects
            ]
            assert camera >= 16.0 * 0.99 or max(objects, default=0.0) >= 22.0 * 0.99


def _peak_object_flow(obj) -> float:
    r = obj.radius
    corners = np.array([[-r, r, r, -r], [-r, -r, r, r], [1.0] * 4])
    return peak_flow_px(obj.motion, corners, 1.5, 1 / 30)


def test_transfer_and_traffic_draws_stay_inside_their_ranges():
    frame_s = 1 / 30
    transfer = [spec.config() for spec in list_sequences("synthetic-transfer-train")[:24]]
    families = set()
    for config in transfer:
        families |= {config.texture.family} | {o.texture.family for o in config.objects}
        s = config.sensor
        assert 0.12 <= s.contrast_threshold <= 0.5 and 0.05 * s.contrast_threshold <= s.threshold_sigma <= 0.2 * s.contrast_threshold + 1e-9
        assert 0.01 <= s.noise_rate_hz <= 1.0 and 0 <= s.hot_pixels <= 10
        assert peak_flow_px(config.camera, config.sensor_size, 1.0, frame_s) <= 15.0 * 1.01
    assert families <= set(TRANSFER_FACTORS.families) and "natural" in families
    traffic = list_sequences("synthetic-traffic")
    assert len(traffic) == 4 and all(spec.duration_s == 1.5 for spec in traffic)
    for spec in traffic:
        config = spec.config()
        assert config.sensor_size in TRAFFIC_FACTORS.sizes
        assert peak_flow_px(config.camera, config.sensor_size, 1.5, frame_s) == 0.0  # a fixed camera
        assert 1 <= len(config.objects) <= 4
        assert all(0.5 * 0.99 <= _peak_object_flow(o) <= 8.0 * 1.01 for o in config.objects)
        assert 0.1 <= config.sensor.noise_rate_hz <= 1.0 and 2 <= config.sensor.hot_pixels <= 12
    # seeds apart from every other split: no validation or held-out sequence is a training one
    seeds = {name: {spec.seed for spec in list_sequences(name)} for name in
             ("synthetic-dr-train", "synthetic-dr-val", "synthetic-transfer-train", "synthetic-transfer-val", "synthetic-traffic")}
    assert sum(len(v) for v in seeds.values()) == len(set().union(*seeds.values()))


def test_transfer_series_extends_like_the_randomised_one():
    specs = list_sequences("synthetic-transfer-train")
    more = list_sequences("synthetic-transfer-train:300")
    assert len(specs) == 256 and len(more) == 300 and more[:256] == specs
    assert get_spec("synthetic-transfer-train:300", 299).name == "synthetic-transfer-train-00299"
    assert all(spec.factors == "transfer" for spec in more)
    with pytest.raises(ValueError, match="positive integer"):
        list_sequences("synthetic-transfer-train:x")
    with pytest.raises(ValueError, match="synthetic-transfer-train:N"):
        list_sequences("synthetic-nowhere")


def test_same_seed_same_bytes(tmp_path):
    spec = next(s for s in list_sequences("synthetic-dr-train") if (s.height, s.width) == (64, 64))
    config = spec.config()
    assert config == spec.config() and SceneConfig.from_dict(json.loads(json.dumps(config.to_dict()))) == config
    a, b = simulate(config, 0.3), simulate(spec.config(), 0.3)
    for field in "xytp":
        assert getattr(a.events, field).tobytes() == getattr(b.events, field).tobytes()
    assert a.frames.tobytes() == b.frames.tobytes()
    assert a.flow_between(0, 33333)[0].tobytes() == b.flow_between(0, 33333)[0].tobytes()
    other = simulate(dataclasses.replace(config, seed=config.seed + 1), 0.3)
    assert len(other.events) != len(a.events) or not np.array_equal(other.events.t, a.events.t)


def test_load_dr_sequence_and_write_every_format(tmp_path, monkeypatch):
    from envs.readers import open_recording

    monkeypatch.setenv("EVFLOW_CACHE", str(tmp_path / "cache"))
    clear_cache()
    try:
        index = next(i for i, s in enumerate(list_sequences("synthetic-dr-train")) if (s.height, s.width) == (64, 64))
        reader = load_sequence("synthetic-dr-train:300", index)  # cached in the default split's folder
        (path,) = (tmp_path / "cache" / "synthetic" / "synthetic-dr-train").glob("*.h5")
        assert reader.sensor_size == (64, 64) and reader.num_events > 0
        grid = reader.flow_timestamps()
        assert len(grid) == 31 and reader.flow_between(int(grid[0]), int(grid[1]))[0].shape == (2, 64, 64)
        reader.close()
    finally:
        clear_cache()
    seq = simulate(SceneConfig.random(2, 24, 40, speed_px_s=90.0), 0.2)
    for fmt in OUTPUT_FORMATS:
        written = write_sequence(seq, tmp_path / fmt / "seq", fmt, name="seq")
        with open_recording(written) as back:
            events = back.events_range(0, back.num_events)
            assert back.sensor_size == (24, 40)
            for field in "xytp":
                np.testing.assert_array_equal(getattr(events, field), getattr(seq.events, field))
            np.testing.assert_array_equal(back.frame(2), seq.frames[2])
            if fmt != "ecd-text":  # text holds no ground truth
                grid = back.flow_timestamps()
                np.testing.assert_allclose(back.flow_between(int(grid[1]), int(grid[2]))[0], seq.flow_between(int(grid[1]), int(grid[2]))[0], atol=1e-5)


def test_generate_split_in_worker_processes_and_into_the_cache(tmp_path, monkeypatch):
    from envs.readers import open_recording

    written = generate_split("synthetic-mini", tmp_path / "out", fmt="hagenaars", num=2, workers=2, progress=False)
    assert [p.name for p in written] == ["synthetic-mini-0.h5", "synthetic-mini-1.h5"]
    exact = get_spec("synthetic-mini", 1).simulate()
    with open_recording(written[1]) as reader:  # a worker's file: the same sequence, byte for byte
        np.testing.assert_array_equal(reader.events_range(0, reader.num_events).t, exact.events.t)
    assert generate_split("synthetic-mini", tmp_path / "out", fmt="hagenaars", num=2, progress=False) == []  # kept
    monkeypatch.setenv("EVFLOW_CACHE", str(tmp_path / "cache"))
    clear_cache()
    try:
        (cached,) = generate_split("synthetic-mini", None, num=1, progress=False)
        stamp = cached.stat().st_mtime_ns
        reader = load_sequence("synthetic-mini", 0)  # found in the cache, not simulated again
        assert isinstance(reader, SyntheticH5Reader) and cached.stat().st_mtime_ns == stamp
        assert reader.num_events == len(get_spec("synthetic-mini", 0).simulate().events)
        reader.close()
        process = start_generation("synthetic-mini", num=2)  # the next one, in the background
        process.join(timeout=120)
        assert process.exitcode == 0
        assert len(list((tmp_path / "cache" / "synthetic" / "synthetic-mini").glob("synthetic-mini-1-*.h5"))) == 1
    finally:
        clear_cache()


def test_env_trains_on_random_crops_of_the_randomised_split():
    from envs.env import EventFlowEnv

    clear_cache()
    try:
        env = EventFlowEnv(data="synthetic-dr-train:1", crop=(64, 64), random_crop=True)
        _, info = env.reset(seed=0)
        assert info["sequence"] == "synthetic-dr-train-00000" and info["flow_gt"].shape == (2, 64, 64)
        *_, info = env.step(np.zeros(env.action_space.shape, np.float32))
        assert np.isfinite(info["flow_gt"]).all()
        env.close()
    finally:
        clear_cache()


# --- synthetic-train-soft: the training scenes with weaker textures ----------------------------


def test_soft_split_is_the_training_scenes_with_their_texture_range_drawn_lower():
    """Each synthetic-train-soft sequence is its synthetic-train twin (same seed, motion bound,
    camera, objects, sensor) except the leaves' log-intensity range, drawn log-uniformly in
    SOFT_CONTRAST; synthetic-train itself is unchanged (its cache keys predate the field)."""
    from envs.synthetic import SOFT_CONTRAST, SPLITS

    soft, train = SPLITS["synthetic-train-soft"], SPLITS["synthetic-train"]
    assert len(soft) == len(train) == 32
    assert train[0].cache_key() == "4a575e5e10" and train[1].cache_key() == "00a74c072b"
    ranges = []
    for a, b in zip(soft, train):
        ca, cb = a.config().to_dict(), b.config().to_dict()
        ranges.append(-ca["texture"]["log_min"])
        assert SOFT_CONTRAST[0] <= ranges[-1] <= SOFT_CONTRAST[1]
        assert 2.0 <= -cb["texture"]["log_min"] <= 3.0
        ca["texture"].pop("log_min"), cb["texture"].pop("log_min")
        assert ca == cb and a.max_flow_px == b.max_flow_px
        assert a.cache_key() != b.cache_key()
    assert np.ptp(np.log(ranges)) > 0.6 * np.log(SOFT_CONTRAST[1] / SOFT_CONTRAST[0])  # spread over the range
    with pytest.raises(ValueError, match="contrast"):
        SceneConfig.random(1, 32, 32, contrast=(1.0, 0.5))


def test_sparse_split_is_the_training_scenes_with_larger_leaves():
    """Each synthetic-train-sparse sequence is its synthetic-train twin but for the smallest leaf
    radius, drawn log-uniformly in SPARSE_LEAVES (synthetic-train: 1.5-3); the other splits' keys
    are unchanged by the field."""
    from envs.synthetic import SPARSE_LEAVES, SPLITS

    sparse, train = SPLITS["synthetic-train-sparse"], SPLITS["synthetic-train"]
    assert len(sparse) == len(train) == 32
    assert train[0].cache_key() == "4a575e5e10" and SPLITS["synthetic-train-soft"][0].leaf_size is None
    radii = []
    for a, b in zip(sparse, train):
        ca, cb = a.config().to_dict(), b.config().to_dict()
        radii.append(ca["texture"]["r_min"])
        assert SPARSE_LEAVES[0] <= radii[-1] <= SPARSE_LEAVES[1]
        assert 1.5 <= cb["texture"]["r_min"] <= 3.0
        ca["texture"].pop("r_min"), cb["texture"].pop("r_min")
        assert ca == cb and a.max_flow_px == b.max_flow_px and a.cache_key() != b.cache_key()
    assert np.ptp(np.log(radii)) > 0.6 * np.log(SPARSE_LEAVES[1] / SPARSE_LEAVES[0])
    with pytest.raises(ValueError, match="leaf_size"):
        SceneConfig.random(1, 32, 32, leaf_size=(8.0, 4.0))


def test_larger_leaves_same_motion_fewer_active_pixels_that_follow_the_truth():
    """The same scene and motion with 8x larger smallest leaves fires on far fewer pixels (fewer
    edges), with about as many events per firing pixel (the same contrasts), and they still follow
    the ground truth. An object's small texture canvas caps the leaves instead of failing."""
    h, w = 48, 64
    active, per_pixel = {}, {}
    for r_min in (2.0, 16.0):
        config = SceneConfig.random(12, h, w, speed_px_s=120.0, leaf_size=(r_min, r_min), noise=False)
        seq = simulate(config, duration_s=0.2)
        t0, t1 = int(seq.frame_times[2]), int(seq.frame_times[3])
        events = seq.events.slice_time(t0, t1)
        counts = np.bincount(np.asarray(events.y, np.int64) * w + np.asarray(events.x, np.int64), minlength=h * w)
        active[r_min], per_pixel[r_min] = (counts > 0).mean(), counts[counts > 0].mean()
        flow, _ = seq.flow_between(t0, t1)
        assert _iwe_variance(events, flow, t0, t1) > 1.1 * _iwe_variance(events, 0 * flow, t0, t1)
    assert active[16.0] < 0.6 * active[2.0]
    assert 0.5 < per_pixel[16.0] / per_pixel[2.0] < 2.0


def test_weaker_texture_same_motion_fewer_events_that_follow_the_truth():
    """The same scene and motion with a 4x smaller log-intensity range fires several times fewer
    events (each edge crosses fewer thresholds), and they still follow the ground truth."""
    h, w = 48, 64
    counts = {}
    for log_range in (0.5, 2.0):
        config = SceneConfig.random(11, h, w, speed_px_s=120.0, contrast=(log_range, log_range), noise=False)
        seq = simulate(config, duration_s=0.2)
        counts[log_range] = len(seq.events.t)
        t0, t1 = int(seq.frame_times[2]), int(seq.frame_times[3])
        flow, _ = seq.flow_between(t0, t1)
        events = seq.events.slice_time(t0, t1)
        sharp = _iwe_variance(events, flow, t0, t1)
        assert sharp > 1.1 * _iwe_variance(events, 0 * flow, t0, t1)
    assert 2.0 < counts[2.0] / counts[0.5] < 6.0
