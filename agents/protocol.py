"""The policy protocol every flow network honours, and a runtime check of it.

A flow network is a *pure* ``torch.nn.Module``::

    flows, state = model(x, state)

- ``x``: (B, C_in, H, W) float32, the event count image of one window (C_in = 2, eq. 2), any
  H and W.
- ``state``: ``None`` for the first window of a sequence, else the dict the previous call
  returned. A dict of tensors, each with leading batch dimension B; a model with no memory
  returns an empty dict. The state holds *everything* carried between windows (hidden states,
  the prior flow, ...); the model keeps nothing between calls.
- ``flows``: a non-empty list of (B, 2, h_l, w_l) tensors, coarsest first, finest last; the
  finest is at full (H, W) resolution. Every scale is in pixels of displacement over the window
  in *full-resolution* units (a coarse scale is not divided by its stride); channel 0 = x
  (right), channel 1 = y (down).

The rule that lets a wrapper reset single batch elements: **an all-zeros state entry for a batch
element is exactly equivalent to a fresh sequence (``state=None``) for that element.**
:class:`agents.policy.RecurrentPolicy` resets element b by zeroing ``state[key][b]`` for every
key, so a model whose fresh state is not zero must map zeros to it itself.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn


class ModelLoadError(ValueError):
    """A model spec could not be turned into a working model (bad name, import, attribute)."""


class ProtocolError(ModelLoadError):
    """A module does not honour the ``forward(x, state) -> (flows, state)`` protocol."""


def _check_output(output, batch: int, size: tuple[int, int], where: str) -> tuple[list[Tensor], dict]:
    if not isinstance(output, (tuple, list)) or len(output) != 2:
        raise ProtocolError(f"{where}: forward must return (flows, state), got {type(output).__name__}")
    flows, state = output
    if not isinstance(flows, (list, tuple)) or len(flows) == 0:
        raise ProtocolError(f"{where}: flows must be a non-empty list of tensors (finest last)")
    for i, flow in enumerate(flows):
        if not isinstance(flow, Tensor) or flow.dim() != 4 or flow.shape[:2] != (batch, 2):
            shape = tuple(flow.shape) if isinstance(flow, Tensor) else type(flow).__name__
            raise ProtocolError(f"{where}: flows[{i}] must be (B={batch}, 2, h, w), got {shape}")
    if tuple(flows[-1].shape[-2:]) != size:
        raise ProtocolError(
            f"{where}: the finest flow (last) must be at the input resolution {size}, "
            f"got {tuple(flows[-1].shape[-2:])}"
        )
    if not all(torch.isfinite(flow).all() for flow in flows):
        raise ProtocolError(f"{where}: flows contain non-finite values")
    if not isinstance(state, dict):
        raise ProtocolError(f"{where}: state must be a dict of tensors (empty if stateless)")
    for key, value in state.items():
        if not isinstance(value, Tensor) or value.dim() == 0 or value.shape[0] != batch:
            raise ProtocolError(f"{where}: state[{key!r}] must be a tensor with leading dim B={batch}")
    return list(flows), state


def check_protocol(
    model: nn.Module, in_channels: int = 2, size: tuple[int, int] = (20, 36), batch: int = 2
) -> None:
    """Raise :class:`ProtocolError` unless ``model`` honours the protocol.

    Runs three small forward passes (no grad, eval mode, restored afterwards): a fresh window, a
    second window with the returned state, and the fresh window again with an all-zeros state,
    which must give the same flows as ``state=None`` (the zero-state rule). ``size`` is
    deliberately not a multiple of 16.
    """
    if not isinstance(model, nn.Module):
        raise ProtocolError(f"a flow model must be a torch.nn.Module, got {type(model).__name__}")
    generator = torch.Generator().manual_seed(0)
    first = torch.randint(0, 4, (batch, in_channels, *size), generator=generator).float()
    second = torch.randint(0, 4, (batch, in_channels, *size), generator=generator).float()
    try:
        parameter = next(model.parameters())
        first, second = first.to(parameter.device), second.to(parameter.device)
    except StopIteration:
        pass
    was_training = model.training
    model.eval()
    try:
        with torch.no_grad():
            try:
                output = model(first, None)
            except Exception as error:  # noqa: BLE001 - reported with context
                raise ProtocolError(f"forward(x, None) failed: {error!r}") from error
            flows, state = _check_output(output, batch, size, "window 1")
            try:
                output = model(second, state)
            except Exception as error:  # noqa: BLE001
                raise ProtocolError(f"forward(x, state) with the returned state failed: {error!r}") from error
            _check_output(output, batch, size, "window 2")
            zeros = {key: torch.zeros_like(value) for key, value in state.items()}
            zero_flows, _ = _check_output(model(first, zeros), batch, size, "zero state")
            for fresh, zeroed in zip(flows, zero_flows):
                if not torch.allclose(fresh, zeroed, rtol=1e-4, atol=1e-4):
                    raise ProtocolError(
                        "an all-zeros state must be equivalent to state=None (a fresh sequence)"
                    )
    finally:
        model.train(was_training)
