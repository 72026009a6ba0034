"""The policy interface, and the stateful wrapper that turns a pure flow network into the
environment's actor.

A flow policy (:class:`FlowPolicy`) is anything with ``reset(mask=None)`` and
``act(obs, window=None) -> flow``: the observation of a window and that window itself (its events,
``info["window"]``), so a policy that solves the window from its events (contrast maximisation,
refinement, sub-windows) is a policy like any other; one that needs only the observation ignores
the window. A plug-in written against ``act(obs)`` alone still plugs in: :func:`as_flow_policy`
passes it the observation only. ``agents.rollout.rollout`` drives any of them through an env;
the wrappers that change how a policy acts (mirror, split, refine, ...) are in
``agents/wrappers/``.

The network is pure (``flows, state = model(x, state)``, see ``agents/protocol.py``); the
wrapper holds the state between windows and offers what rollouts and truncated BPTT need::

    policy = RecurrentPolicy(make_model("ev-mgrflownet", width="cpu"))
    policy.reset()                       # new sequences for every batch element
    action = policy.act(observation)     # rollout: numpy in, numpy out, no grad
    flows = policy(count_images)         # training: differentiable, updates the state
    policy.detach()                      # truncated BPTT: cut the graph to earlier windows
    policy.reset(mask=done)              # vector env: new sequences where an episode ended

Mixed precision (``autocast``): the network's forward runs under ``torch.autocast`` in bfloat16
or float16, and what leaves it (the flows, the recurrent state) is float32 again, so the losses
and the state carried between windows stay float32 (:func:`autocast_dtype` reads ``--amp``).
"""

from __future__ import annotations

import inspect
from typing import Protocol, runtime_checkable

import numpy as np
import torch
from torch import Tensor, nn

from envs.representations import OBSERVATIONS
from envs.windows import Window

State = dict[str, Tensor]

#: ``--amp`` values: auto (bf16 on a CUDA device that supports it, else off), bf16, fp16 (CUDA only), off
AMP_CHOICES = ("auto", "bf16", "fp16", "off")


def autocast_dtype(amp: str, device: torch.device | str) -> torch.dtype | None:
    """The dtype the network's forward autocasts to for ``--amp`` on ``device`` (None: float32).

    auto: bfloat16 on a CUDA device that supports it, else float32 (on CPU the measured speed-up
    of bf16 does not pay for its rounding, docs/training.md); bf16: bfloat16 (ValueError on a CUDA
    device without it); fp16: float16, CUDA only (its gradients need loss scaling, which the
    learner does there); off: float32."""
    if amp not in AMP_CHOICES:
        raise ValueError(f"amp must be one of {AMP_CHOICES}, got {amp!r}")
    device = torch.device(device)
    cuda = device.type == "cuda"
    if amp == "auto":
        return torch.bfloat16 if cuda and torch.cuda.is_bf16_supported() else None
    if amp == "bf16":
        if cuda and not torch.cuda.is_bf16_supported():
            raise ValueError(f"amp bf16: {torch.cuda.get_device_name(device)} does not support bfloat16; "
                             "use --amp fp16 or off")
        return torch.bfloat16
    if amp == "fp16":
        if not cuda:
            raise ValueError(f"amp fp16 needs a CUDA device (this run: {device}); on CPU use --amp bf16 or off")
        return torch.float16
    return None


@runtime_checkable
class FlowPolicy(Protocol):
    """What the rollout, the evaluation, predict and every wrapper act through.

    ``reset(mask=None)``: start new sequences (all, or where the (B,) bool ``mask`` is True).
    ``act(obs, window=None)``: the flow for one window, (2, H, W) float32 pixels of displacement
    over the window; ``obs`` is the env's observation dict, ``window`` the env's
    ``info["window"]`` (an ``envs.windows.Window``: its events ``window.events`` and bounds
    ``window.t_start``, ``window.t_end``). A policy that does not need the window ignores it; one that does
    raises ValueError without it.

    Optional attributes, read with these defaults: ``input_key`` ("count_image"), the
    observation part it reads, and ``voxel_bins`` (5), that part's size when it is a voxel grid.
    """

    def reset(self, mask=None) -> None: ...

    def act(self, obs, window: Window | None = None) -> np.ndarray: ...


class ZeroFlowPolicy:
    """Zero flow on every window: the baseline every method is measured against."""

    input_key = "count_image"
    voxel_bins = 5

    def reset(self, mask=None) -> None:
        """Nothing to reset."""

    def act(self, obs, window: Window | None = None) -> np.ndarray:
        return np.zeros((2, *np.shape(obs[self.input_key])[-2:]), np.float32)


class ObservationOnlyPolicy:
    """A plug-in whose ``act`` takes the observation alone (``act(obs)``), as a :class:`FlowPolicy`:
    the window is not passed on. Every other attribute is the plug-in's."""

    def __init__(self, policy) -> None:
        self.policy = policy

    def reset(self, mask=None) -> None:
        if mask is None:
            self.policy.reset()  # a plug-in's reset() may take no mask
        else:
            self.policy.reset(mask)

    def act(self, obs, window: Window | None = None) -> np.ndarray:
        return self.policy.act(obs)

    def __getattr__(self, name: str):
        if name == "policy":  # not set yet (copying, unpickling): no recursion
            raise AttributeError(name)
        return getattr(self.policy, name)


def as_flow_policy(policy) -> FlowPolicy:
    """``policy`` itself when its ``act`` takes the window, else (a plug-in's ``act(obs)``) wrapped
    in :class:`ObservationOnlyPolicy`. The one place where the two kinds are told apart: by the
    signature of ``act``, which takes a second positional argument or not."""
    try:
        parameters = inspect.signature(policy.act).parameters.values()
    except (TypeError, ValueError):  # no signature to read (a builtin): assume the interface
        return policy
    positional = [p for p in parameters if p.kind in (p.POSITIONAL_ONLY, p.POSITIONAL_OR_KEYWORD)]
    if len(positional) >= 2 or any(p.kind == p.VAR_POSITIONAL for p in parameters):
        return policy
    return ObservationOnlyPolicy(policy)


class RecurrentPolicy(nn.Module):
    """Holds a flow model's recurrent state across windows.

    Args:
        model: a module honouring the protocol (``forward(x, state) -> (flows, state)``).
        device: where to run it; None keeps the device of the model's parameters (CPU if none).
        input_key: the observation part fed to the model, one of envs.representations.OBSERVATIONS:
            "count_image" (paper, 2 channels), "voxel_grid" (voxel_bins channels) or
            "count_time_image" (EV-FlowNet's 4 channels).
        autocast: torch.bfloat16 or torch.float16 to run the network's forward in mixed precision
            (flows and state leave it as float32); None: float32 throughout.
    """

    def __init__(
        self,
        model: nn.Module,
        device: torch.device | str | None = None,
        *,
        input_key: str = "count_image",
        voxel_bins: int = 5,
        autocast: torch.dtype | None = None,
    ):
        super().__init__()
        self.autocast = autocast  # the forward's reduced precision (None: float32)
        if input_key not in OBSERVATIONS:  # read from checkpoints and provenance files: checked, not trusted
            raise ValueError(f"input_key must be one of {tuple(OBSERVATIONS)}, got {input_key!r}")
        if not 1 <= int(voxel_bins) <= 64:
            raise ValueError(f"voxel_bins must be in [1, 64], got {voxel_bins!r}")
        self.input_key = input_key  # which observation part the model reads
        self.voxel_bins = int(voxel_bins)  # its size, when the input is "voxel_grid"
        if device is None:
            parameter = next(model.parameters(), None)
            device = parameter.device if parameter is not None else torch.device("cpu")
        self.device = torch.device(device)
        self.model = model.to(self.device)
        self._state: State | None = None

    @classmethod
    def from_pretrained(cls, name: str | None = None, device: torch.device | str | None = "cpu") -> "RecurrentPolicy":
        """The actor of a shipped pretrained model (see ``agents/pretrained.py``), reading the
        observation part it was trained on."""
        from .pretrained import load_pretrained

        model, info = load_pretrained(name, map_location=device or "cpu")
        return cls(model, device=device, input_key=info["input"], voxel_bins=info["voxel_bins"])

    @property
    def state(self) -> State | None:
        """The state the next window continues from (None = fresh sequence for every element)."""
        return self._state

    @state.setter
    def state(self, value: State | None) -> None:
        self._state = None if value is None else dict(value)

    def reset(self, mask: np.ndarray | Tensor | None = None) -> None:
        """Start new sequences: for all batch elements (``mask=None``) or where ``mask`` is True.

        mask: (B,) bool. Masked elements get an all-zeros state, which the protocol defines as a
        fresh sequence; the others keep theirs (and their graph).
        """
        if mask is None or self._state is None:
            self._state = None
            return
        mask = torch.as_tensor(np.asarray(mask) if not isinstance(mask, Tensor) else mask)
        mask = mask.to(device=self.device, dtype=torch.bool).reshape(-1)
        new_state = {}
        for key, value in self._state.items():
            if value.shape[0] != mask.shape[0]:
                raise ValueError(
                    f"reset mask has {mask.shape[0]} elements but the state batch is {value.shape[0]}"
                )
            where = mask.view(-1, *([1] * (value.dim() - 1)))
            new_state[key] = torch.where(where, torch.zeros((), dtype=value.dtype, device=value.device), value)
        self._state = new_state

    def detach(self) -> None:
        """Cut the graph between the windows seen so far and the next ones (truncated BPTT)."""
        if self._state is not None:
            self._state = {key: value.detach() for key, value in self._state.items()}

    def forward(self, x: Tensor | np.ndarray) -> list[Tensor]:
        """Differentiable step: x (B, C_in, H, W) -> flows (finest last, pixels), state updated."""
        x = torch.as_tensor(x, dtype=torch.float32, device=self.device)
        if self._state:
            batch = next(iter(self._state.values())).shape[0]
            if x.shape[0] != batch:
                raise ValueError(
                    f"batch size changed from {batch} to {x.shape[0]} mid-sequence; call reset() first"
                )
        if self.autocast is None:
            flows, self._state = self.model(x, self._state)
            return flows
        with torch.autocast(self.device.type, dtype=self.autocast):
            flows, state = self.model(x, self._state)
        # the recurrence carried in float32
        self._state = {key: value.float() if value.is_floating_point() else value for key, value in state.items()}
        return [flow.float() for flow in flows]

    @torch.no_grad()
    def act(self, obs: dict | np.ndarray | Tensor, window: Window | None = None) -> np.ndarray:
        """Rollout step without gradients (:class:`FlowPolicy`).

        obs: an env observation dict with ``input_key`` ("count_image" (2, H, W) by default)
            for a single env, or (B, C, H, W) for a vector env; or that array itself.
        window: not read (the network sees the observation only).
        Returns: the finest flow, float32 numpy, (2, H, W) or (B, 2, H, W), pixels over the window.
        """
        part = obs[self.input_key] if isinstance(obs, dict) else obs
        x = torch.as_tensor(np.asarray(part) if not isinstance(part, Tensor) else part)
        single = x.dim() == 3
        if single:
            x = x.unsqueeze(0)
        flow = self.forward(x)[-1].float().cpu().numpy()
        return flow[0] if single else flow
