"""Smooth affine motion of one scene layer (the camera's background plane or one object).

A layer carries its own 2-D coordinates ``q`` (pixels, origin at the layer's centre). At time
``t`` (seconds) a layer point is seen at image position

    object layers (camera=False):  p(t) = anchor + T(t) + s(t) R(theta(t)) q
        the object moves by T and turns and scales about its own centre;
    the camera's plane (camera=True):  p(t) = anchor + s(t) R(theta(t)) (q - T(t))
        the camera pans by T over the plane and rolls and zooms about the image point
        ``anchor`` (the image centre), so rotation and zoom speeds stay bounded in view;

with
    T(t)     = velocity * t + acceleration * t^2 / 2
               + trans_amp * sin(2 pi trans_freq t + trans_phase)
               + shake_amp * sin(2 pi shake_freq t + shake_phase)                  (per axis)
    theta(t) = angle0 + angular_velocity * t + rot_amp * sin(2 pi rot_freq t + rot_phase)
    s(t)     = scale0 * exp(zoom_rate * t + zoom_amp * sin(2 pi zoom_freq t + zoom_phase))

(the second sinusoid is a fast "shake"; acceleration and zoom_rate give speeds that change
within a window and a steady zoom in or out; all default to zero),

so the map from layer to image at time t is the affine matrix ``A(t)`` (3x3, homogeneous) and
the exact displacement of the point seen at pixel ``p`` at ``t0`` is ``A(t1) A(t0)^-1 p - p``.
Image coordinates are ``(x, y)`` = (column, row), pixel centres on integers, y pointing down,
so a positive angle turns +x towards +y (clockwise on screen).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["AffineMotion"]

Pair = tuple[float, float]


@dataclass(frozen=True)
class AffineMotion:
    """Parameters of a layer's motion (module docstring gives the two forms).

    Units: positions and amplitudes in pixels, velocities in px/s, angles in radians,
    angular velocity in rad/s, frequencies in Hz, ``zoom_amp`` in log-scale units.
    """

    # The defaults describe a still layer: every term off (scale 1). Alike in shape only to the
    # other simulator settings (FactorRanges, SensorConfig): different quantities.
    anchor: Pair = (0.0, 0.0)
    velocity: Pair = (0.0, 0.0)
    trans_amp: Pair = (0.0, 0.0)
    trans_freq: Pair = (0.0, 0.0)
    trans_phase: Pair = (0.0, 0.0)
    angle0: float = 0.0
    angular_velocity: float = 0.0
    rot_amp: float = 0.0
    rot_freq: float = 0.0
    rot_phase: float = 0.0
    scale0: float = 1.0
    zoom_amp: float = 0.0
    zoom_freq: float = 0.0
    zoom_phase: float = 0.0
    camera: bool = False
    acceleration: Pair = (0.0, 0.0)
    shake_amp: Pair = (0.0, 0.0)
    shake_freq: Pair = (0.0, 0.0)
    shake_phase: Pair = (0.0, 0.0)
    zoom_rate: float = 0.0

    @classmethod
    def from_dict(cls, d: dict) -> "AffineMotion":
        return cls(**{k: tuple(v) if isinstance(v, list) else v for k, v in d.items()})

    def params(self, t: float) -> tuple[float, float, float, float]:
        """(tx, ty, theta, scale) at time t seconds: the translation T(t) in pixels (without
        the anchor), the angle in radians and the scale factor."""
        two_pi = 2.0 * np.pi
        tx = self.velocity[0] * t + self.trans_amp[0] * np.sin(two_pi * self.trans_freq[0] * t + self.trans_phase[0])
        ty = self.velocity[1] * t + self.trans_amp[1] * np.sin(two_pi * self.trans_freq[1] * t + self.trans_phase[1])
        theta = self.angle0 + self.angular_velocity * t + self.rot_amp * np.sin(two_pi * self.rot_freq * t + self.rot_phase)
        # the terms added later are skipped at zero, so older configs compute bit for bit as before
        if self.acceleration != (0.0, 0.0):
            tx = tx + 0.5 * self.acceleration[0] * t * t
            ty = ty + 0.5 * self.acceleration[1] * t * t
        if self.shake_amp != (0.0, 0.0):
            tx = tx + self.shake_amp[0] * np.sin(two_pi * self.shake_freq[0] * t + self.shake_phase[0])
            ty = ty + self.shake_amp[1] * np.sin(two_pi * self.shake_freq[1] * t + self.shake_phase[1])
        log_scale = self.zoom_amp * np.sin(two_pi * self.zoom_freq * t + self.zoom_phase)
        if self.zoom_rate != 0.0:
            log_scale = log_scale + self.zoom_rate * t
        scale = self.scale0 * np.exp(log_scale)
        return float(tx), float(ty), float(theta), float(scale)

    def matrix(self, t: float) -> np.ndarray:
        """A(t): (3, 3) float64, image coordinates from layer coordinates (homogeneous)."""
        tx, ty, theta, s = self.params(t)
        c, si = s * np.cos(theta), s * np.sin(theta)
        ax, ay = self.anchor
        if self.camera:  # anchor + sR (q - T)
            ox, oy = ax - (c * tx - si * ty), ay - (si * tx + c * ty)
        else:  # anchor + T + sR q
            ox, oy = ax + tx, ay + ty
        return np.array([[c, -si, ox], [si, c, oy], [0.0, 0.0, 1.0]])

    def inverse(self, t: float) -> np.ndarray:
        """A(t)^-1: (3, 3) float64, layer coordinates from image coordinates (closed form)."""
        a = self.matrix(t)
        # A = [[sR, o], [0, 1]]  ->  A^-1 = [[R^T / s, -R^T o / s], [0, 1]]
        lin = a[:2, :2].T / (a[0, 0] ** 2 + a[1, 0] ** 2)
        inv = np.eye(3)
        inv[:2, :2] = lin
        inv[:2, 2] = -lin @ a[:2, 2]
        return inv

    def transfer(self, t0: float, t1: float) -> np.ndarray:
        """A(t1) A(t0)^-1: (3, 3) float64, image position at t1 of the layer point seen at p at t0."""
        return self.matrix(t1) @ self.inverse(t0)
