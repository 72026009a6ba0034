"""Event recordings as a Gymnasium environment.

Importing ``envs`` registers the environment ids (Gymnasium 1.x has no entry-point plugins):

- ``EventFlow-v0``: the synthetic benchmark's train split by default; any ``data=`` works.
- ``EventFlowTest-v0``: the same env on the synthetic test split.

>>> import gymnasium, envs
>>> env = gymnasium.make("EventFlow-v0")
"""

import gymnasium

from envs.events import EventError, Events

__all__ = ["Events", "EventError", "EventFlowEnv", "ENV_IDS"]

ENV_IDS = ("EventFlow-v0", "EventFlowTest-v0")


def _register() -> None:
    if "EventFlow-v0" in gymnasium.registry:
        return
    gymnasium.register("EventFlow-v0", entry_point="envs.env:EventFlowEnv", kwargs={"data": "synthetic-train"})
    # synthetic-test holds 128x128 and 256x256 sequences: the registered env shows the central
    # 128x128 of each (one frame for the spaces); scripts/evaluate.py scores each whole
    gymnasium.register("EventFlowTest-v0", entry_point="envs.env:EventFlowEnv",
                       kwargs={"data": "synthetic-test", "crop": (128, 128)})


_register()


def __getattr__(name):
    if name == "EventFlowEnv":  # lazy: keeps `import envs.events` light
        from envs.env import EventFlowEnv

        return EventFlowEnv
    raise AttributeError(name)
