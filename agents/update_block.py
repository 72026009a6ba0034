"""A learned finish: a small recurrent update block that reads, at each of K iterations, what a
solve step reads (the gradient of the window's loss with respect to the flow) and what the
window's events look like under the current flow (their warped image: where they pile up and
how sharply), and writes a correction to the flow. It is the amortised counterpart of the
K-step solve of ``agents/wrappers/refine.py``, trained on the simulator's windows from the shipped
network's proposals, toward a lower loss after its K iterations or toward the ``--cmax`` solve
from zero flow (``scripts/train_block.py``). Measured on devval it stays behind the default's
20-step solve, so the default does not use it (docs/finish.md, "A learned finish")::

    block = UpdateBlock()
    finished = learned_finish(block, proposal, window.batch(), steps=4, frames=4.0)

Everything runs on a grid ``scale`` (4) times coarser than the sensor's; the correction is
upsampled bilinearly (a smooth correction, as the solve's correction grids are), times the
window's length in frames (the block thinks in pixels per 30 Hz frame). The block starts as the
identity (its last layer is zero), so an untrained block returns the proposal. Between
iterations the features are detached (as RAFT does with its flow): the gradient of the training
loss reaches the block through its corrections, not through the loss's own second derivative,
which keeps an update's cost near that of K solve steps.
"""

from __future__ import annotations

import torch
import torch.nn as nn
import torch.nn.functional as F

from losses import CMAX_WEIGHTS, LossSpec, window_loss, zero_flow_loss
from losses.events import EventBatch
from losses.iwe import warped_event_images
from losses.sampling import sample_flow

__all__ = ["UpdateBlock", "block_features", "learned_finish", "load_block", "FEATURES", "BLOCK_KIND"]

#: the input channels, in order
FEATURES = ("flow_x", "flow_y", "grad_x", "grad_y", "log_count", "log_sharpness", "log_frames")
#: the loss the block finishes on by default: the solve's (agents.cmax.CMaxSettings: the env's
#: reward with the stronger smoothness term, flow scaling 32 pixels)
SPEC, FLOW_SCALING = CMAX_WEIGHTS, 32.0
_EPS = 1e-12


def block_features(flow: torch.Tensor, events: EventBatch, frames: torch.Tensor, *, scale: int = 4,
                   spec: LossSpec = SPEC, flow_scaling: float | None = FLOW_SCALING,
                   zero: torch.Tensor | None = None) -> torch.Tensor:
    """(B, 7, ceil(H / scale), ceil(W / scale)) detached inputs of :class:`UpdateBlock` for the
    flow (B, 2, H, W) in pixels per window on the B windows of ``events``: the flow in pixels per
    frame; the gradient of the windows' loss (``spec``, flow scaling max(H, W), border rule
    against ``zero``; ``flow_scaling`` None: max(H, W)) with respect to it, each window's divided by its mean magnitude; the log of
    the mean warped-event count (events warped to mid-window, both polarities) per coarse cell
    and of the mean squared count over the mean count (high where the events pile up sharply);
    the log of the window's length in frames."""
    B, _, height, width = flow.shape
    size = (-(-height // scale), -(-width // scale))
    frames = frames.reshape(B, 1, 1, 1).to(flow)
    with torch.enable_grad():
        current = flow.detach().requires_grad_()
        scaling = float(max(height, width)) if flow_scaling is None else float(flow_scaling)
        loss = window_loss(current, events, spec, flow_scaling=scaling, zero_flow=zero)
        (gradient,) = torch.autograd.grad(loss.per_sample.sum(), current)
    with torch.no_grad():
        u = sample_flow(current.detach(), events.x, events.y, events.mask)
        count, _ = warped_event_images(events.zero_padding(), u, height, width, references=(0.5,))
        count = count[:, 0].sum(1, keepdim=True)  # (B, 1, H, W): both polarities
        mean = F.adaptive_avg_pool2d(count, size)
        square = F.adaptive_avg_pool2d(count * count, size)
        gradient = F.adaptive_avg_pool2d(gradient, size)
        gradient = gradient / gradient.abs().mean(dim=(1, 2, 3), keepdim=True).clamp_min(_EPS)
        moved = F.adaptive_avg_pool2d(flow.detach(), size) / frames
        features = torch.cat([moved, gradient, torch.log1p(mean), torch.log1p(square / (mean + 1e-6)),
                              torch.log(frames).expand(B, 1, *size)], dim=1)
    return features


class _ConvGRU(nn.Module):
    def __init__(self, hidden: int, inputs: int) -> None:
        super().__init__()
        self.gates = nn.Conv2d(hidden + inputs, 2 * hidden, 3, padding=1)
        self.candidate = nn.Conv2d(hidden + inputs, hidden, 3, padding=1)

    def forward(self, h: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        z, r = torch.sigmoid(self.gates(torch.cat([h, x], 1))).chunk(2, 1)
        q = torch.tanh(self.candidate(torch.cat([r * h, x], 1)))
        return (1 - z) * h + z * q


class UpdateBlock(nn.Module):
    """The learned update (module docstring): an encoder of :func:`block_features` (three 3x3
    convolutions, dilated 1-2-4, so one cell sees 15 coarse cells across), a convolutional GRU
    whose state carries over the K iterations of one finish, and a head that writes the
    correction in pixels per frame on the coarse grid. ``hidden`` channels; ``scale``: the
    coarsening of the sensor grid it works on; ``cells``: the correction is averaged onto a grid
    of this many cells along the longer side before it is upsampled (the solve's finest grid, 16:
    a correction as smooth as the solve's; 0: none, the block's own grid)."""

    def __init__(self, hidden: int = 32, scale: int = 4, cells: int = 16) -> None:
        super().__init__()
        if int(hidden) < 1 or int(scale) < 1 or int(cells) < 0:
            raise ValueError(f"UpdateBlock: hidden and scale must be >= 1 and cells >= 0, got {hidden}, {scale}, {cells}")
        self.hidden, self.scale, self.cells = int(hidden), int(scale), int(cells)
        c = self.hidden
        self.encoder = nn.Sequential(
            nn.Conv2d(len(FEATURES), c, 3, padding=1), nn.ReLU(),
            nn.Conv2d(c, c, 3, padding=2, dilation=2), nn.ReLU(),
            nn.Conv2d(c, c, 3, padding=4, dilation=4), nn.ReLU(),
        )
        self.gru = _ConvGRU(c, c)
        self.head = nn.Sequential(nn.Conv2d(c, c, 3, padding=1), nn.ReLU(), nn.Conv2d(c, 2, 3, padding=1))
        nn.init.zeros_(self.head[-1].weight)
        nn.init.zeros_(self.head[-1].bias)

    def initial_state(self, features: torch.Tensor) -> torch.Tensor:
        """The GRU's state at the start of a finish: zeros shaped like the coarse grid."""
        B, _, h, w = features.shape
        return features.new_zeros(B, self.hidden, h, w)

    def forward(self, features: torch.Tensor, state: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(correction (B, 2, h, w) in pixels per frame, next state (B, hidden, h, w))."""
        state = self.gru(state, self.encoder(features))
        return self.head(state), state

    def config(self) -> dict:
        return {"hidden": self.hidden, "scale": self.scale, "cells": self.cells}

    def smooth(self, correction: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
        """The coarse correction upsampled bilinearly to ``size`` (H, W), through the ``cells`` grid."""
        height, width = size
        if self.cells:
            grid = (max(1, round(self.cells * height / max(height, width))),
                    max(1, round(self.cells * width / max(height, width))))
            if grid[0] < correction.shape[-2] or grid[1] < correction.shape[-1]:
                correction = F.adaptive_avg_pool2d(correction, grid)
        return F.interpolate(correction, size=(height, width), mode="bilinear", align_corners=False)


def learned_finish(block: UpdateBlock, proposal: torch.Tensor, events: EventBatch, *, steps: int,
                   frames: float | torch.Tensor, spec: LossSpec = SPEC, flow_scaling: float | None = FLOW_SCALING,
                   return_all: bool = False):
    """(B, 2, H, W) ``proposal`` (pixels per window) finished by ``steps`` iterations of
    ``block`` on the B windows of ``events`` (``frames``: each window's length in 30 Hz frames,
    one number or (B,)); ``spec`` and ``flow_scaling``: the loss whose gradient it reads (the
    solve's by default; None: max(H, W)). Differentiable in the block's weights (not in the proposal); under
    ``torch.no_grad`` it is the test-time finish. ``return_all``: the list of the flows after
    each iteration instead (training takes its loss on each)."""
    if int(steps) < 0:
        raise ValueError(f"learned_finish: steps must be >= 0, got {steps}")
    B, _, height, width = proposal.shape
    frames_t = torch.as_tensor(frames, dtype=torch.float32, device=proposal.device).reshape(-1)
    if frames_t.numel() == 1:
        frames_t = frames_t.expand(B)
    if frames_t.numel() != B or not bool(torch.isfinite(frames_t).all()) or bool((frames_t <= 0).any()):
        raise ValueError(f"learned_finish: frames must be one positive length or one per window ({B}), got {frames}")
    proposal = proposal.detach().float()
    scaling = float(max(height, width)) if flow_scaling is None else float(flow_scaling)
    zero = zero_flow_loss(proposal, events, spec, flow_scaling=scaling).per_sample
    flow, state, flows = proposal, None, []
    for _ in range(int(steps)):
        features = block_features(flow, events, frames_t, scale=block.scale, spec=spec, flow_scaling=scaling,
                                  zero=zero)
        if state is None:
            state = block.initial_state(features)
        correction, state = block(features, state)
        correction = block.smooth(correction, (height, width))
        flow = flow + correction * frames_t.reshape(B, 1, 1, 1)
        flows.append(flow)
    if return_all:
        return flows
    return flow


def frames_of(duration_us: float) -> float:
    """A window's length in 30 Hz frames, at least 1 (the solve's convention, agents.cmax)."""
    from .cmax import FRAME_US

    return max(1.0, float(duration_us) / FRAME_US)


#: the checkpoint kind of scripts/train_block.py
BLOCK_KIND = "evflow-update-block"


def load_block(path, device: str | torch.device = "cpu") -> tuple[UpdateBlock, dict]:
    """(block in eval mode, payload) from a file of ``scripts/train_block.py`` (loaded with
    ``torch.load(weights_only=True)``: no code from the file runs). ValueError naming the file
    when it holds something else."""
    from .checkpoint import load_checkpoint

    payload = load_checkpoint(path, map_location=device, required=("kind",))
    if payload.get("kind") != BLOCK_KIND:
        kind = payload.get("kind")
        raise ValueError(f"{path}: not an update block of scripts/train_block.py (kind {kind!r})")
    config = payload.get("block_config") or {}
    try:
        block = UpdateBlock(**config)
        block.load_state_dict(payload["block"])
    except (TypeError, KeyError, RuntimeError, ValueError) as err:
        raise ValueError(f"{path}: the update block's weights do not load ({err})") from err
    return block.to(device).eval(), payload
