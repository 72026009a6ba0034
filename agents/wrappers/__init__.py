"""Policy wrappers: each takes a flow policy (``agents.policy.FlowPolicy``) and is one, acting
differently on each window. The evaluation's extra rows and the cheap modes of
``tools/cheap_modes.py`` are built from them.

- :class:`MirrorPolicy` (``mirror.py``, ``evaluate.py --mirror``): the flow averaged over
  mirrored copies of the input;
- :class:`SubWindowPolicy` (``subwindows.py``, ``--split``): stepped through equal sub-windows of
  each window, their flows composed;
- :class:`RefinedPolicy` (``refine.py``, ``--refine``): the flow refined by contrast
  maximisation on the window's events;
- :class:`StillGuard` (``still.py``, ``--still``): zero flow wherever the flow does not lower
  the window's loss below zero flow's;
- :class:`CoarsePolicy` (``coarse.py``): the events binned on a coarser grid, the flow upsampled;
- :class:`GainPolicy` (``gain.py``): the flow times a constant;
- :class:`CombinedPolicy` (``combine.py``): several policies' mean flow, or the flow the window's
  events prefer.

Wrappers nest (``SubWindowPolicy(MirrorPolicy(net), 4)``, ``RefinedPolicy(SubWindowPolicy(...))``).
"""

from .coarse import CoarsePolicy
from .combine import CombinedPolicy
from .gain import GainPolicy
from .mirror import MIRROR_SETS, MIRRORS, ROTATION, MirrorPolicy
from .refine import RefinedPolicy
from .still import StillGuard
from .subwindows import SubWindowPolicy, compose_flows, sub_windows

__all__ = ["CoarsePolicy", "CombinedPolicy", "GainPolicy", "MIRRORS", "MIRROR_SETS", "MirrorPolicy", "ROTATION",
           "RefinedPolicy", "StillGuard", "SubWindowPolicy", "compose_flows", "sub_windows"]
