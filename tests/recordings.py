"""Small recordings with known motion for the tests: envs/recordings.py (in the package, so the
benchmarks run from an installed wheel too)."""

from envs.recordings import translating_dots, write_translating_recording

__all__ = ["translating_dots", "write_translating_recording"]
