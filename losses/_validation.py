"""Input checks shared by the losses: clear ValueErrors instead of silent garbage."""

from __future__ import annotations

import torch

from .events import EventBatch


def check_flow(flow: torch.Tensor, name: str = "flow") -> None:
    """flow: (B, 2, H, W) floating tensor, finite, B > 0."""
    if not isinstance(flow, torch.Tensor):
        raise ValueError(f"{name} must be a torch.Tensor, got {type(flow).__name__}")
    if flow.ndim != 4 or flow.shape[1] != 2:
        raise ValueError(f"{name} must have shape (B, 2, H, W), got {tuple(flow.shape)}")
    if not flow.is_floating_point():
        raise ValueError(f"{name} must be a floating tensor, got {flow.dtype}")
    if flow.shape[0] == 0:
        raise ValueError(f"{name}: empty batch (B = 0)")
    if flow.shape[2] == 0 or flow.shape[3] == 0:
        raise ValueError(f"{name}: empty image (H, W) = {tuple(flow.shape[2:])}")
    # one reduction: a NaN/inf anywhere makes the sum non-finite (exact check only then, since
    # huge finite values can also overflow the sum)
    if not bool(torch.isfinite(flow.sum())) and not bool(torch.isfinite(flow).all()):
        raise ValueError(f"{name} contains NaN or inf")


def check_events(events: EventBatch, batch_size: int | None = None, name: str = "events") -> None:
    """All fields (B, N), B > 0 (and == batch_size if given), tau in [0, 1] for valid events."""
    if not isinstance(events, EventBatch):
        raise ValueError(f"{name} must be an EventBatch, got {type(events).__name__}")
    shape = events.x.shape
    if len(shape) != 2:
        raise ValueError(f"{name}: fields must be (B, N), x has shape {tuple(shape)}")
    for field in ("y", "tau", "p", "mask"):
        if getattr(events, field).shape != shape:
            raise ValueError(
                f"{name}: field {field!r} has shape {tuple(getattr(events, field).shape)}, "
                f"x has {tuple(shape)}"
            )
    if events.mask.dtype != torch.bool:
        raise ValueError(f"{name}: mask must be bool, got {events.mask.dtype}")
    if shape[0] == 0:
        raise ValueError(f"{name}: empty batch (B = 0)")
    if batch_size is not None and shape[0] != batch_size:
        raise ValueError(f"batch size mismatch: flow has B = {batch_size}, {name} has B = {shape[0]}")
    if shape[1] == 0:
        return
    m = events.mask  # no compiled kernel: one gained under 10 % of a training or env step
    kind, b, i = 0, -1, -1
    for code, bad in ((1, m & ~((events.tau >= 0) & (events.tau <= 1))),  # also catches NaN
                      (2, m & ~(torch.isfinite(events.x) & torch.isfinite(events.y)))):
        if bool(bad.any()):
            kind, (b, i) = code, (int(v) for v in bad.nonzero()[0])
            break
    if kind == 1:
        raise ValueError(
            f"{name}: tau[{b}, {i}] = {float(events.tau[b, i])} is outside [0, 1] "
            "(event time outside its window)"
        )
    if kind == 2:
        raise ValueError(f"{name}: x or y at [{b}, {i}] is NaN or inf")
