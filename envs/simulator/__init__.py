"""Synthetic event-camera simulator: the project's embedded default data and its only source
of exact ground-truth flow.

ESIM-style: a layered scene (a dead-leaves background plane moved by the camera's smooth affine
motion, plus textured objects with their own motion, occluding in depth order) is rendered in
log intensity at adaptive sub-steps (no visible point moves more than 0.25 px per step), and an
event fires each time a pixel's log intensity crosses its reference by its contrast threshold.

    from envs.simulator import SceneConfig, simulate
    seq = simulate(SceneConfig.random(seed=0, height=128, width=128, speed_px_s=150), duration_s=1.0)
    seq.events                      # Events, t in us
    seq.flow_between(t0_us, t1_us)  # exact (flow (2,H,W) float32 px, valid (H,W) bool all True)
    seq.frames, seq.frame_times     # (F,H,W) uint8, (F,) int64 us
    reader = seq.reader("demo")     # an ArrayReader for the rest of the project

Modules: ``motion`` (affine layer motion), ``textures`` (dead leaves and other procedural
families), ``scene`` (configs, rendering, exact flow), ``emulator`` (the event camera model),
``simulate`` (the loop), ``randomize`` (scenes drawn from ranges of every factor: the
domain-randomised and the held-out stress splits).
"""

from envs.simulator.emulator import EventEmulator
from envs.simulator.motion import AffineMotion
from envs.simulator.scene import ObjectSpec, Scene, SceneConfig, SensorConfig
from envs.simulator.simulate import SIMULATOR_VERSION, SimulatedSequence, log_to_uint8, simulate
from envs.simulator.textures import TextureConfig, make_texture

__all__ = [
    "AffineMotion",
    "EventEmulator",
    "ObjectSpec",
    "Scene",
    "SceneConfig",
    "SensorConfig",
    "SimulatedSequence",
    "SIMULATOR_VERSION",
    "TextureConfig",
    "log_to_uint8",
    "make_texture",
    "simulate",
]
