"""Checkpoints that cannot be half-written and are safe to load.

A checkpoint is a dict saved with ``torch.save``:

    format: "evflow-checkpoint", version: 2
    model_name: registry name or "package.module:factory"; model_config: its kwargs (a dotted
        path is rebuilt only when the user names it too: :func:`load_model`)
    model: state_dict; optimizer, scheduler: state_dicts (training checkpoints)
    step: optimizer steps done; config: the training configuration (a dict)
    rng: python / numpy / torch generator states, and CUDA's of the training device only
    policy_state: the recurrent state carried into the next unroll (tensors on CPU)
    env_states: every training env's episode state (see EventFlowEnv.episode_state)

Safe schema: what is stored holds only tensors, numbers, strings, booleans, None, lists, tuples
and dicts, so it loads with ``torch.load(weights_only=True)``, which runs no code from the file.
:func:`save_checkpoint` converts numpy arrays (``{"__ndarray__": tensor, "dtype": ...}``, or the
elements of an object array), numpy scalars and other mappings on the way in, and
:func:`load_checkpoint` turns them back into numpy arrays and dicts. Anything else is refused
when saving. A file written before (version 1, pickled numpy objects) raises
:class:`CheckpointError` telling to convert it once with :func:`upgrade_checkpoint`
(``python scripts/export_model.py --upgrade FILE``), which must unpickle it: only for files you trust.

Writes go to ``<name>.tmp-<host>-<pid>`` and are renamed over the target when complete; temporaries of
killed writers are removed by the next save to that name (:mod:`envs.atomic`).
"""

from __future__ import annotations

import io
import os
import pickle
import random
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import torch

from envs.atomic import write_atomic
from envs.windows import Window

from .registry import MODELS, make_model

__all__ = [
    "save_checkpoint",
    "load_checkpoint",
    "load_model",
    "upgrade_checkpoint",
    "to_safe",
    "from_safe",
    "rng_state",
    "set_rng_state",
    "CheckpointError",
    "check_model_name",
]

FORMAT = "evflow-checkpoint"
VERSION = 2
_NDARRAY = "__ndarray__"
_OBJECTS = "__ndarray_objects__"


class CheckpointError(ValueError):
    """A file that is not a checkpoint of this project (the message names the file)."""


def rng_state(device: str | torch.device | None = None) -> dict[str, Any]:
    """Python, numpy and torch generator states, plus CUDA's of ``device`` when it is a CUDA
    device (only that one: other GPUs are neither needed nor touched, and a CPU run never
    initialises CUDA)."""
    state = {"python": random.getstate(), "numpy": np.random.get_state(), "torch": torch.get_rng_state()}
    device = None if device is None else torch.device(device)
    if device is not None and device.type == "cuda":
        state["cuda"] = torch.cuda.get_rng_state(device)
    return state


def set_rng_state(state: dict[str, Any], device: str | torch.device | None = None) -> None:
    """Restore :func:`rng_state`; the CUDA state goes to ``device`` when both are CUDA."""
    random.setstate(state["python"])
    np.random.set_state(state["numpy"])
    torch.set_rng_state(state["torch"])
    device = None if device is None else torch.device(device)
    cuda = state.get("cuda")
    if cuda is not None and device is not None and device.type == "cuda":
        if isinstance(cuda, (list, tuple)):  # version 1 stored every GPU's state: take this device's
            index = device.index if device.index is not None else torch.cuda.current_device()
            if index >= len(cuda):
                return
            cuda = cuda[index]
        torch.cuda.set_rng_state(cuda, device)


def to_safe(value: Any, where: str = "checkpoint") -> Any:
    """``value`` in the safe schema (module docstring): numpy arrays become tagged tensors (object
    arrays: their elements), numpy scalars Python numbers, mappings dicts, an env's ``Window`` the
    dict of its events and bounds. Raises TypeError naming
    the entry (``where``) for anything else."""
    if value is None or isinstance(value, (bool, int, float, str, torch.Tensor)):
        return value
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        if value.dtype.kind in "biuf":
            return {_NDARRAY: torch.from_numpy(np.array(value, value.dtype.newbyteorder("="))), "dtype": value.dtype.str.lstrip("<>=|")}
        return {_OBJECTS: [to_safe(v, f"{where}[{i}]") for i, v in enumerate(value.ravel().tolist())],
                "shape": list(value.shape)}
    if isinstance(value, Window):  # a window in the env's info: its events and bounds, as the window dict was
        events = value.events
        return to_safe({"x": events.x, "y": events.y, "t": events.t, "p": events.p, "t_start": value.t_start,
                        "t_end": value.t_end}, where)
    if isinstance(value, Mapping):
        out = {}
        for key, item in value.items():
            if not isinstance(key, (str, int)):
                raise TypeError(f"{where}: key {key!r} is neither a string nor an int; cannot be saved safely")
            out[key] = to_safe(item, f"{where}/{key}")
        return out
    if isinstance(value, (list, tuple)):
        items = [to_safe(v, f"{where}[{i}]") for i, v in enumerate(value)]
        return items if isinstance(value, list) else tuple(items)
    raise TypeError(f"{where}: a {type(value).__name__} cannot be saved safely (allowed: tensors, numbers, strings, "
                    "lists, tuples, dicts, numpy arrays)")


def from_safe(value: Any) -> Any:
    """Inverse of :func:`to_safe`: tagged tensors back to numpy arrays."""
    if isinstance(value, dict):
        if _NDARRAY in value:
            return value[_NDARRAY].cpu().numpy().astype(np.dtype(value["dtype"]), copy=False)
        if _OBJECTS in value:
            items = [from_safe(v) for v in value[_OBJECTS]]
            array = np.empty(len(items), object)
            array[:] = items
            return array.reshape(value["shape"])
        return {key: from_safe(item) for key, item in value.items()}
    if isinstance(value, list):
        return [from_safe(v) for v in value]
    if isinstance(value, tuple):
        return tuple(from_safe(v) for v in value)
    return value


def save_checkpoint(path: str | os.PathLike, payload: dict[str, Any]) -> Path:
    """Write ``payload`` (see the module docstring) atomically: the old file stays intact until
    the new one is complete on disk. Raises TypeError, before writing, for an entry outside the
    safe schema."""
    path = Path(path)
    safe = to_safe({"format": FORMAT, **payload, "version": VERSION})
    buffer = io.BytesIO()
    torch.save(safe, buffer)
    return write_atomic(path, buffer.getvalue())


def load_checkpoint(path: str | os.PathLike, map_location: str | torch.device = "cpu",
                    required: tuple[str, ...] = ("model_name", "model_config", "model")) -> dict[str, Any]:
    """Load a checkpoint with ``torch.load(weights_only=True)`` (no code from the file runs).
    ``required``: the entries it must hold (a network's, by default).

    Raises CheckpointError naming the file for a missing, truncated or foreign file, and for a
    checkpoint in the old pickled format (with the command that converts it)."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{path}: no such checkpoint")
    try:
        payload = torch.load(path, map_location=map_location, weights_only=True)
    except pickle.UnpicklingError as err:
        if "weights_only" in str(err) or "Weights only load failed" in str(err):
            raise CheckpointError(
                f"{path}: holds pickled Python objects, which a safe load refuses (a checkpoint written before "
                f"format version {VERSION}, or not one of ours). If you trust the file, convert it once: "
                f"python scripts/export_model.py --upgrade {path}"
            ) from None
        raise CheckpointError(f"{path}: not a readable checkpoint (UnpicklingError: {err})") from err
    except Exception as err:  # truncated or foreign files
        raise CheckpointError(f"{path}: not a readable checkpoint ({type(err).__name__}: {err})") from err
    if not isinstance(payload, dict) or payload.get("format") != FORMAT:
        raise CheckpointError(f"{path}: not an evflow checkpoint (missing 'format': {FORMAT!r})")
    for key in required:
        if key not in payload:
            raise CheckpointError(f"{path}: checkpoint lacks {key!r}")
    return from_safe(payload)


def upgrade_checkpoint(path: str | os.PathLike, out: str | os.PathLike | None = None) -> Path:
    """Convert an old-format (pickled) checkpoint to the safe schema, in place or to ``out``;
    returns the path written. This unpickles the file, which can run code: only for trusted files.
    A file that already loads safely is rewritten unchanged in content."""
    path = Path(path)
    out = path if out is None else Path(out)
    try:
        payload = load_checkpoint(path)
    except CheckpointError:
        try:
            payload = torch.load(path, map_location="cpu", weights_only=False)
        except Exception as err:
            raise CheckpointError(f"{path}: not a readable checkpoint ({type(err).__name__}: {err})") from err
        if not isinstance(payload, dict) or payload.get("format") != FORMAT:
            raise CheckpointError(f"{path}: not an evflow checkpoint (missing 'format': {FORMAT!r})") from None
    save_checkpoint(out, payload)
    load_checkpoint(out)  # proves the result loads safely
    return out


def load_model(
    path: str | os.PathLike, map_location: str | torch.device = "cpu", *, expect_model: str | None = None,
    plugin: str | None = None,
) -> tuple[torch.nn.Module, dict]:
    """Rebuild the model stored in a checkpoint; returns (model in eval mode, checkpoint).

    The file's ``model_name`` must be a registered model (``agents.registry.MODELS``): a dotted
    path ``package.module:factory`` imports and runs code, so it is taken only when the caller's
    user named that same path (``plugin``, or ``expect_model``): a checkpoint alone never
    chooses the code that runs. ``model_config`` must be a dict of keyword arguments.

    expect_model: raise CheckpointError unless the checkpoint holds this model (registry name
    or dotted path). Weights that do not fit the rebuilt model raise CheckpointError too.
    """
    payload = load_checkpoint(path, map_location)
    name = payload["model_name"]
    if expect_model is not None and expect_model != name:
        raise CheckpointError(f"{path}: checkpoint holds model {name!r}, not {expect_model!r}")
    check_model_name(name, path, trusted=plugin or expect_model)
    config = payload["model_config"]
    if not isinstance(config, dict) or not all(isinstance(k, str) for k in config):
        raise CheckpointError(f"{path}: model_config must be a dict of keyword arguments, got {type(config).__name__}")
    try:
        model = make_model(name, **config)
    except (TypeError, ValueError) as err:
        raise CheckpointError(f"{path}: model {name!r} cannot be built with config {config}: {err}") from err
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


def check_model_name(name: Any, source: str | os.PathLike, trusted: str | None = None) -> str:
    """``name``, a model name read from a file (``source``: a checkpoint, campaign or export),
    if it is a registered model, or a dotted path equal to ``trusted`` (the one the user named
    on their own command line or in code). Anything else raises CheckpointError naming the file:
    a file never picks code to import."""
    if not isinstance(name, str) or not name:
        raise CheckpointError(f"{source}: model name must be a non-empty string, got {name!r}")
    if name in MODELS and ":" not in name:
        return name
    if ":" in name and trusted is not None and name == trusted:
        return name
    if ":" in name:
        raise CheckpointError(
            f"{source}: names the plug-in model {name!r} (a dotted path, whose import runs code); a file may only "
            f"name a registered model ({', '.join(sorted(MODELS))}). If you trust this file and that code, name the "
            f"plug-in yourself (evaluate.py --checkpoint FILE --model {name}, predict.py FILE --model FILE --plugin {name}, "
            f"train.py --resume/--init with --model {name}, "
            f"or load_model(path, plugin={name!r}))")
    raise CheckpointError(f"{source}: unknown model {name!r}; registered: {', '.join(sorted(MODELS))} "
                          "(a model registered with agents.register_model must be registered before loading)")
