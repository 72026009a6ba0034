"""The event camera model (ESIM-style): log-intensity frames in, events out.

Every pixel keeps a reference log intensity ``ref`` (initialised to the first frame). Between
two consecutive renders ``L_a`` (time ``t_a``) and ``L_b`` (time ``t_b``) the log intensity is
taken as linear in time; each time it crosses ``ref + j * C_on`` (rising, j = 1, 2, ...) or
``ref - j * C_off`` (falling) the pixel fires an ON / OFF event at the linearly interpolated
crossing time, so a large change gives several events. ``C_on`` and ``C_off`` are drawn once per
pixel (normal around the contrast threshold). After a step the reference has moved by all the
crossings (``ref += n * C``), so it always stays within one threshold of the current value.

Refractory period: a crossing less than ``refractory_us`` after the pixel's last *emitted*
event is dropped (not emitted), but the reference still moves past it, as a real pixel that
resets to the current level once it wakes up.

Noise (optional): background-activity events, Poisson in space-time with ``noise_rate_hz`` per
pixel and random polarity, and hot pixels, a few fixed pixels firing at ``hot_pixel_rate_hz``
with a fixed polarity. Noise does not touch the references. With ``noise_refractory`` the
refractory period applies to every event, noise included, in time order per pixel.

Optional sensor effects (all off by default):

- ON/OFF imbalance: mean thresholds ``C sqrt(r)`` (ON) and ``C / sqrt(r)`` (OFF), r = ``on_off_ratio``.
- Leak: the reference sinks at ``leak_rate_hz * C_on`` per second (per-pixel rate x0.5-1.5,
  random initial phase), so a still pixel fires ON events at about ``leak_rate_hz``. Within a
  step the reference is linear in time, like the intensity, so crossing times stay exact.
- Bandwidth: the sensed log intensity ``F`` follows the rendered ``L`` through a first-order
  low-pass, ``dF/dt = (L - F) / tau``, with ``tau = bandwidth_tau_us * min(exp(-L), 100)``
  (``L`` clipped at 0 from above: bandwidth grows with intensity up to its bright value).
  Over a step ``L`` is linear with slope ``k`` and ``tau`` is taken at the step's start, so
  ``F(t_b) = L_b - k tau + (F(t_a) - L_a + k tau) exp(-dt / tau)`` exactly; the crossings are
  then found on ``F`` as above.

All work is vectorised over pixels; the only Python loop is over the crossing rank ``j``
(at most a handful per sub-step when the sub-steps are small).
"""

from __future__ import annotations

import numpy as np

from envs.simulator.scene import SensorConfig

__all__ = ["EventEmulator"]


class EventEmulator:
    """Turns a sequence of log-intensity renders into events.

    log_intensity: (H, W) float32, the first render (sets the references).
    sensor: the :class:`SensorConfig`. rng: the generator for thresholds and noise.
    """

    def __init__(self, log_intensity: np.ndarray, sensor: SensorConfig, rng: np.random.Generator) -> None:
        self.sensor = sensor
        self.height, self.width = log_intensity.shape
        n = log_intensity.size
        self.ref = log_intensity.astype(np.float32).ravel().copy()
        c = sensor.contrast_threshold
        imbalance = np.sqrt(sensor.on_off_ratio)  # exactly 1.0 when balanced: C itself
        self.c_on = np.maximum(rng.normal(c * imbalance, sensor.threshold_sigma, n), sensor.min_threshold).astype(np.float32)
        self.c_off = np.maximum(rng.normal(c / imbalance, sensor.threshold_sigma, n), sensor.min_threshold).astype(np.float32)
        self.last_event_us = np.full(n, -np.inf)
        self.rng = rng
        self.hot_index = rng.choice(n, size=min(sensor.hot_pixels, n), replace=False)
        self.hot_polarity = rng.choice(np.array([-1, 1], np.int8), size=len(self.hot_index))
        # the optional effects draw only when on, so a sensor without them keeps its random stream
        self.leak_per_us = None
        if sensor.leak_rate_hz > 0:
            self.leak_per_us = (sensor.leak_rate_hz * 1e-6 * rng.uniform(0.5, 1.5, n) * self.c_on).astype(np.float32)
            self.ref -= (rng.uniform(0.0, 1.0, n) * self.c_on).astype(np.float32)  # random leak phase
        self.sensed = log_intensity.astype(np.float64).ravel().copy() if sensor.bandwidth_tau_us > 0 else None

    def step(self, previous: np.ndarray, current: np.ndarray, t_a: int, t_b: int):
        """Events fired while the log intensity goes from ``previous`` at t_a to ``current`` at
        t_b (integer microseconds, t_b > t_a).

        previous, current: (H, W) float32 log intensities.
        Returns (x, y, t, p): int16, int16, int64 us in [t_a, t_b), int8; sorted by t.
        """
        span = float(t_b - t_a)
        if self.sensed is not None:
            previous, current = self._low_pass(previous, current, span)
        leak = None
        if self.leak_per_us is not None:
            # in the frame of the reference at t_a: the intensity gains what the reference loses
            leak = self.leak_per_us * np.float32(span)
            current = current.ravel() + leak
        joint_refractory = self.sensor.noise_refractory and self.sensor.refractory_us > 0
        diff = current.ravel() - self.ref
        n_on = np.floor(diff / self.c_on)
        n_off = np.floor(-diff / self.c_off)
        active = np.flatnonzero((n_on >= 1) | (n_off >= 1))
        pixels, times, polarity = [], [], []
        if len(active):
            on = n_on[active] >= 1
            count = np.where(on, n_on[active], n_off[active]).astype(np.int64)
            step_c = np.where(on, self.c_on[active], -self.c_off[active])
            start = previous.ravel()[active]
            change = current.ravel()[active] - start
            change = np.where(change == 0, np.float32(1e-12), change)
            ref = self.ref[active]
            last = self.last_event_us[active]
            sign = np.where(on, 1, -1).astype(np.int8)
            # with a joint refractory period every candidate passes here and is filtered below
            refractory = 0.0 if joint_refractory else float(self.sensor.refractory_us)
            for j in range(1, int(count.max()) + 1):
                pending = np.flatnonzero(count >= j)
                frac = np.clip((ref[pending] + j * step_c[pending] - start[pending]) / change[pending], 0.0, 1.0)
                t = t_a + frac * span
                fire = t >= last[pending] + refractory
                firing = pending[fire]
                last[firing] = t[fire]
                pixels.append(active[firing])
                times.append(t[fire])
                polarity.append(sign[firing])
            self.ref[active] = ref + count * step_c
            if not joint_refractory:
                self.last_event_us[active] = last
        if leak is not None:
            self.ref -= leak

        # background activity and hot pixels (do not touch the references)
        dt_s = (t_b - t_a) * 1e-6
        n_noise = self.rng.poisson(self.sensor.noise_rate_hz * self.height * self.width * dt_s) if self.sensor.noise_rate_hz > 0 else 0
        if n_noise:
            pixels.append(self.rng.integers(0, self.height * self.width, n_noise))
            times.append(self.rng.uniform(t_a, t_b, n_noise))
            polarity.append(self.rng.choice(np.array([-1, 1], np.int8), n_noise))
        if len(self.hot_index):
            hot_counts = self.rng.poisson(self.sensor.hot_pixel_rate_hz * dt_s, len(self.hot_index))
            if hot_counts.any():
                pixels.append(np.repeat(self.hot_index, hot_counts))
                times.append(self.rng.uniform(t_a, t_b, int(hot_counts.sum())))
                polarity.append(np.repeat(self.hot_polarity, hot_counts))

        if not pixels:
            return _empty()
        pixels = np.concatenate(pixels)
        if len(pixels) == 0:
            return _empty()
        times = np.concatenate(times)
        polarity = np.concatenate(polarity)
        if joint_refractory:
            keep = self._refractory_filter(pixels, times)
            pixels, times, polarity = pixels[keep], times[keep], polarity[keep]
        order = np.argsort(times, kind="stable")
        t_us = np.clip(np.floor(times[order]).astype(np.int64), t_a, t_b - 1)
        pixels = pixels[order]
        return (
            (pixels % self.width).astype(np.int16),
            (pixels // self.width).astype(np.int16),
            t_us,
            polarity[order].astype(np.int8),
        )

    def _low_pass(self, previous: np.ndarray, current: np.ndarray, span_us: float) -> tuple[np.ndarray, np.ndarray]:
        """The sensed log intensity at the step's start and end (module docstring): (N,) float32 each."""
        start = previous.ravel().astype(np.float64)
        end = current.ravel().astype(np.float64)
        tau = self.sensor.bandwidth_tau_us * np.minimum(np.exp(-np.minimum(start, 0.0)), BANDWIDTH_DARK_FACTOR)
        slope = (end - start) / span_us
        sensed_a = self.sensed
        sensed_b = end - slope * tau + (sensed_a - start + slope * tau) * np.exp(-span_us / tau)
        self.sensed = sensed_b
        return sensed_a.astype(np.float32), sensed_b.astype(np.float32)

    def _refractory_filter(self, pixels: np.ndarray, times: np.ndarray) -> np.ndarray:
        """Which candidate events fire when every event of a pixel silences it for
        refractory_us: (N,) bool. Goes through each pixel's candidates in time order, one
        rank (first, second, ... candidate of its pixel) at a time, updating last_event_us."""
        keep = np.zeros(len(pixels), bool)
        if len(pixels) == 0:
            return keep
        order = np.lexsort((times, pixels))
        sorted_pixels = pixels[order]
        first = np.r_[True, sorted_pixels[1:] != sorted_pixels[:-1]]
        rank = np.arange(len(order)) - np.maximum.accumulate(np.where(first, np.arange(len(order)), 0))
        refractory = float(self.sensor.refractory_us)
        for r in range(int(rank.max()) + 1):
            chosen = order[rank == r]
            pix, t = pixels[chosen], times[chosen]
            fire = t >= self.last_event_us[pix] + refractory
            keep[chosen[fire]] = True
            self.last_event_us[pix[fire]] = t[fire]
        return keep


# longest bandwidth time constant, as a multiple of the bright one (very dark pixels)
BANDWIDTH_DARK_FACTOR = 100.0


def _empty():
    return np.zeros(0, np.int16), np.zeros(0, np.int16), np.zeros(0, np.int64), np.zeros(0, np.int8)
