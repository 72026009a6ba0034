"""Pretrained models shipped with the package, loadable by name.

Each model is two files in ``agents/weights/``: ``NAME.pt``, a weights-only checkpoint (model
name, config and state dict; no optimizer), and ``NAME.json``, its provenance: the command that
trained it, the data, the budget, the date and the measured metrics. Nothing is downloaded.

    from agents.pretrained import load_pretrained, list_pretrained
    policy = RecurrentPolicy.from_pretrained("ev-mgrflownet-cpu-synthetic")
    action = policy.act(observation)          # observation from an EventFlow env

``scripts/export_model.py`` turns a training checkpoint into such a pair.
"""

from __future__ import annotations

import json
import os
import re
from pathlib import Path
from typing import Any

import h5py
import torch

from envs.atomic import write_atomic
from envs.windows import FALLBACK_INTERVAL_US

from .checkpoint import CheckpointError, check_model_name, load_checkpoint, load_model, save_checkpoint
from .provenance import code_version

__all__ = ["WEIGHTS_DIR", "IN_CHECKOUT", "check_writable_checkout", "DEFAULT_PRETRAINED", "default_choice",
           "list_pretrained", "pretrained_info", "load_pretrained", "export_pretrained", "check_model_file_name"]

WEIGHTS_DIR = Path(__file__).resolve().parent / "weights"

#: True when the package runs from a checkout of the repository (the source tree or an editable
#: install). An installed wheel carries the default model only (pyproject.toml's package-data);
#: the other shipped models, the campaigns and the exports live in a checkout.
IN_CHECKOUT = (Path(__file__).resolve().parents[1] / "pyproject.toml").is_file()

CHECKOUT_HINT = ("git clone the repository and pip install -e . inside it (or run from its folder)")


def check_writable_checkout(what: str) -> None:
    """ValueError when ``what`` would write into an installed package (site-packages): exports
    and campaign state are written into a checkout only."""
    if not IN_CHECKOUT:
        raise ValueError(f"{what} writes into the repository's agents/ folder, and this is an installed package "
                         f"({Path(__file__).resolve().parent}), which nothing writes into: {CHECKOUT_HINT}")

#: a shipped model's name: one path component of lower-case letters, digits, '.', '_' and '-'
NAME_PATTERN = re.compile(r"[a-z0-9][a-z0-9._-]{0,99}")


def check_model_file_name(name: object, what: str = "model name") -> str:
    """``name`` if it is a valid shipped model's name (:data:`NAME_PATTERN`, no '..'): the
    export never writes outside its weights folder. ValueError naming the problem otherwise."""
    if not isinstance(name, str) or not NAME_PATTERN.fullmatch(name) or ".." in name:
        raise ValueError(f"{what} {name!r}: must be one file-name component of lower-case letters, digits, '.', '_' "
                         "and '-' (e.g. ev-mgrflownet-cpu-mine), starting with a letter or digit, without '..'")
    return name


def default_choice(directory: str | os.PathLike | None = None) -> dict[str, Any]:
    """The shipped model and mode that a command without a model name uses, and why:
    ``agents/weights/default.json`` (``model``, ``mode``, ``chosen_on``, ``scores``, ``date``),
    chosen on the independent validation set (docs/results.md)."""
    path = Path(WEIGHTS_DIR if directory is None else directory) / "default.json"
    return json.loads(path.read_text())


DEFAULT_PRETRAINED = default_choice()["model"]


def default_split() -> str | None:
    """The default model's mode as a ``--split`` value (``default.json``'s ``split``: ``"dt"``,
    one network step per ground-truth interval), None for one pass or a weights folder without
    ``default.json`` (a folder of one's own models, none chosen as the default)."""
    try:
        return default_choice().get("split")
    except FileNotFoundError:
        return None


def default_finish(choice: dict[str, Any] | None = None) -> list[dict]:
    """The default model's finish (``default.json``'s ``finish``, or ``choice``'s): a list of
    ``agents.wrappers.refine.Finish`` fields, the solve run on each window after the network
    (docs/finish.md); [] for none or a weights folder without ``default.json``."""
    if choice is None:
        try:
            choice = default_choice()
        except FileNotFoundError:
            return []
    return list(choice.get("finish") or [])


def default_steps(window: str, window_size: int | None, frame_us: int = FALLBACK_INTERVAL_US,
                  choice: dict[str, Any] | None = None) -> int:
    """Network steps per window of the default model's mode (:func:`default_split`, or
    ``choice``'s ``split``): ``"dt"``, one step per ground-truth interval: ``window_size`` frames
    (default 1), or a time window of ``window_size`` µs over ``frame_us`` (the interval the model
    steps at, rounded, at least 1); event-count windows and one pass: 1."""
    split = default_split() if choice is None else choice.get("split")
    if split != "dt":
        return 1
    if window == "frames":
        return int(window_size or 1)
    if window == "time" and window_size:
        return max(1, round(int(window_size) / int(frame_us)))
    return 1


def list_pretrained(directory: str | os.PathLike | None = None) -> list[str]:
    """Names of the shipped models (those with both NAME.pt and NAME.json)."""
    directory = Path(WEIGHTS_DIR if directory is None else directory)
    return sorted(p.stem for p in directory.glob("*.pt") if p.with_suffix(".json").exists())


def _paths(name: str, directory: str | os.PathLike | None) -> tuple[Path, Path]:
    directory = Path(WEIGHTS_DIR if directory is None else directory)
    known = list_pretrained(directory)
    if name not in known:
        if not IN_CHECKOUT and directory == WEIGHTS_DIR:
            raise KeyError(f"no pretrained model {name!r} in this installation: the package carries the default "
                           f"only ({', '.join(known) or 'none'}); the repository's other shipped models load by name "
                           f"from a checkout ({CHECKOUT_HINT}), or give the file of a model to --checkpoint")
        raise KeyError(f"no pretrained model {name!r}; shipped: {known or 'none'} (in {directory})")
    return directory / f"{name}.pt", directory / f"{name}.json"


def pretrained_info(name: str, directory: str | os.PathLike | None = None) -> dict[str, Any]:
    """The provenance record of a shipped model (command, data, budget, date, metrics)."""
    return json.loads(_paths(name, directory)[1].read_text())


def load_pretrained(
    name: str | None = None, map_location: str | torch.device = "cpu", directory: str | os.PathLike | None = None
) -> tuple[torch.nn.Module, dict[str, Any]]:
    """(model in eval mode, provenance) of a shipped model. The provenance's ``"input"`` says
    which observation the model reads ("count_image" or "voxel_grid", with ``"voxel_bins"``)."""
    name = DEFAULT_PRETRAINED if name is None else name
    weights, _ = _paths(name, directory)
    model, payload = load_model(weights, map_location=map_location)
    info = pretrained_info(name, directory)
    info.setdefault("input", (payload.get("config") or {}).get("input", "count_image"))
    info.setdefault("voxel_bins", (payload.get("config") or {}).get("voxel_bins", 5))
    return model, info


def export_pretrained(
    checkpoint: str | os.PathLike, name: str, provenance: dict[str, Any], directory: str | os.PathLike | None = None,
    *, overwrite: bool = False,
) -> tuple[Path, Path]:
    """Write ``NAME.pt`` (weights only, float32, CPU) and ``NAME.json`` from a training
    checkpoint. Both files are written atomically; the weights are checked to load first.
    Floating-point weights are stored as float16 (half the size; loading casts them back to the
    model's float32, a relative change below 1e-3 per weight).

    ``name`` must be one file-name component (:func:`check_model_file_name`); a model of that
    name already in ``directory`` is replaced only with ``overwrite`` (FileExistsError otherwise).
    The checkpoint must hold a registered model (a shipped file never names code to import)."""
    check_model_file_name(name)
    if directory is None:
        check_writable_checkout(f"exporting {name!r}")
    directory = Path(WEIGHTS_DIR if directory is None else directory)
    existing = [p.name for p in (directory / f"{name}.pt", directory / f"{name}.json") if os.path.lexists(p)]
    if existing and not overwrite:
        raise FileExistsError(f"{directory}: already holds {', '.join(existing)}; choose another name, or replace "
                              "it on purpose (--overwrite)")
    payload = load_checkpoint(checkpoint)
    check_model_name(payload["model_name"], checkpoint)
    config = payload.get("config") or {}
    slim = {
        "model_name": payload["model_name"],
        "model_config": payload["model_config"],
        "model": {k: v.detach().to("cpu", torch.float16) if v.is_floating_point() else v.cpu()
                  for k, v in payload["model"].items()},
        "step": payload.get("step"),
        "config": config,
    }
    weights = save_checkpoint(directory / f"{name}.pt", slim)
    try:
        load_model(weights)
    except CheckpointError:
        weights.unlink(missing_ok=True)
        raise
    record = {"name": name, "model": payload["model_name"], "model_config": payload["model_config"],
              "input": config.get("input", "count_image"), "voxel_bins": config.get("voxel_bins", 5),
              "steps": payload.get("step"), **provenance}
    record.setdefault("code", code_version())  # the package version and git commit that exported it
    if config.get("teacher_cache") and "teacher_targets" not in record:
        record["teacher_targets"] = _targets_provenance(Path(config["teacher_cache"]))
    meta = directory / f"{name}.json"
    write_atomic(meta, json.dumps(record, indent=2, default=str) + "\n")
    return weights, meta


def _targets_provenance(path: Path) -> dict[str, Any]:
    """How the teacher targets a run regressed onto were made (their file's config: data, window
    lengths, solver settings, and the derivation where they were derived), by file name. Read at
    export: the run's own targets only (a stage started with ``--init`` from a teacher run does
    not carry its parent's), and the file as it is then."""
    try:
        with h5py.File(path, "r") as f:
            config = json.loads(f.attrs.get("config", "null"))
    except (OSError, ValueError) as err:
        return {"file": path.name, "config": None, "error": f"not readable at export ({type(err).__name__})"}
    return {"file": path.name, "config": config}
