"""Checkpoints that cannot be half-written: saved to a temporary file, then renamed.

A checkpoint is a dict saved with ``torch.save``:

    format: "evflow-checkpoint", version: 1
    model_name: registry name or "package.module:factory"; model_config: its kwargs
    model: state_dict; optimizer, scheduler: state_dicts (training checkpoints)
    step: optimizer steps done; config: the training configuration (a dict)
    rng: python / numpy / torch (and CUDA) generator states
    policy_state: the recurrent state carried into the next unroll (tensors on CPU)
    env_states: every training env's episode state (see EventFlowEnv.episode_state)
"""

from __future__ import annotations

import os
import random
from pathlib import Path
from typing import Any

import numpy as np
import torch

from .registry import make_model

__all__ = ["save_checkpoint", "load_checkpoint", "load_model", "rng_state", "set_rng_state", "CheckpointError"]

FORMAT = "evflow-checkpoint"


class CheckpointError(ValueError):
    """A file that is not a checkpoint of this project (the message names the file)."""


def rng_state() -> dict[str, Any]:
    state = {"python": random.getstate(), "numpy": np.random.get_state(), "torch": torch.get_rng_state()}
    if torch.cuda.is_available():
        state["cuda"] = torch.cuda.get_rng_state_all()
    return state


def set_rng_state(state: dict[str, Any]) -> None:
    random.setstate(state["python"])
    np.random.set_state(state["numpy"])
    torch.set_rng_state(state["torch"])
    if "cuda" in state and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(state["cuda"])


def save_checkpoint(path: str | os.PathLike, payload: dict[str, Any]) -> Path:
    """Write ``payload`` (see the module docstring) atomically: the old file stays intact until
    the new one is complete on disk."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f"{path.name}.tmp-{os.getpid()}")
    try:
        with open(tmp, "wb") as f:
            torch.save({"format": FORMAT, "version": 1, **payload}, f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
    return path


def load_checkpoint(path: str | os.PathLike, map_location: str | torch.device = "cpu") -> dict[str, Any]:
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{path}: no such checkpoint")
    try:
        payload = torch.load(path, map_location=map_location, weights_only=False)
    except Exception as err:  # truncated or foreign files
        raise CheckpointError(f"{path}: not a readable checkpoint ({type(err).__name__}: {err})") from err
    if not isinstance(payload, dict) or payload.get("format") != FORMAT:
        raise CheckpointError(f"{path}: not an evflow checkpoint (missing 'format': {FORMAT!r})")
    for key in ("model_name", "model_config", "model"):
        if key not in payload:
            raise CheckpointError(f"{path}: checkpoint lacks {key!r}")
    return payload


def load_model(
    path: str | os.PathLike, map_location: str | torch.device = "cpu", *, expect_model: str | None = None
) -> tuple[torch.nn.Module, dict]:
    """Rebuild the model stored in a checkpoint; returns (model in eval mode, checkpoint).

    expect_model: raise CheckpointError unless the checkpoint holds this model (registry name
    or dotted path). Weights that do not fit the rebuilt model raise CheckpointError too.
    """
    payload = load_checkpoint(path, map_location)
    name = payload["model_name"]
    if expect_model is not None and expect_model != name:
        raise CheckpointError(f"{path}: checkpoint holds model {name!r}, not {expect_model!r}")
    model = make_model(name, **payload["model_config"])
    try:
        model.load_state_dict(payload["model"])
    except RuntimeError as err:
        first = str(err).splitlines()[0:3]
        raise CheckpointError(
            f"{path}: weights do not fit model {name!r} with config {payload['model_config']}: {' '.join(first)}"
        ) from err
    model.to(map_location)
    model.eval()
    return model, payload
