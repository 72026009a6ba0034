"""Campaigns: training that outlives its machine.

A campaign is a named training configuration plus its resumable state, kept in one folder of
the repository (``agents/campaigns/NAME/``) so that a fresh clone on another machine continues
where the last one stopped:

    campaign.json   what the campaign is: train.py's options (the recipe), the weights it starts
                    from, the validation data and score, the export name, the state interval
    state.pt        the slim resume state (a training checkpoint, see :func:`slim_state`):
                    float32 weights, step, scheduler position, RNG, every env's episode position
                    and the recurrent state; Adam's moments only when they fit :data:`STATE_BUDGET`
    curve.jsonl     one line per validation, accumulated across resumes (step, score, AEE per
                    dt, cumulative training hours, the machine)
    reference.json  the reference row of the score (per-window contrast maximisation on the
                    validation data), computed once
    curve.png       the curve, drawn from curve.jsonl

Work in progress (the full training checkpoint with the moments, metrics, logs) lives in
``runs/campaigns/NAME/`` and dies with the machine; the folder above is what survives.
``scripts/campaign.py`` is the command (evflow_cli/commands/campaign.py).
"""

from __future__ import annotations

import io
import json
import os
import platform
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from agents.checkpoint import load_checkpoint, save_checkpoint
from envs.atomic import temporary_path, write_atomic

__all__ = ["CAMPAIGNS_DIR", "STATE_BUDGET", "CampaignSpec", "Campaign", "slim_state", "unslim_state", "machine",
           "plot_curve"]

CAMPAIGNS_DIR = Path(__file__).resolve().parents[1] / "agents" / "campaigns"  # beside the shipped weights
#: the most a campaign's resume state may weigh (bytes): it is committed at every stretch
STATE_BUDGET = 12 * 2**20


@dataclass
class CampaignSpec:
    """What a campaign trains and how it is judged (``campaign.json``)."""

    name: str
    export: str
    """the shipped model (agents/weights/EXPORT.pt/.json) its improved weights are exported to"""
    train: list[str]
    """scripts/train.py options of the recipe (not --out, --resume, --init, --minutes)"""
    init: str | None = None
    """weights the first stretch starts from (a shipped model's name or a checkpoint)"""
    val_data: list[str] = field(default_factory=list)
    """evaluate.py --data of the validation (no validation when empty)"""
    val_dt: list[int] = field(default_factory=lambda: [1, 4])
    val_windows: int | None = None
    """windows per validation sequence (None: all)"""
    val_split: str | None = None
    """the mode the score is taken in: None, one network step per window; "dt", one step per
    ground-truth interval (evaluate.py --split dt, the shipped default's mode until 2026-12-05);
    "finish", one step per window finished by the default's short solve (evaluate.py --finish,
    the shipped default's mode)"""
    reference: str = "cmax"
    """the score's reference row: 'cmax' (per-window contrast maximisation) or 'zero' (zero flow)"""
    interval_minutes: float = 20.0
    """training between two validations and state writes"""
    state_budget_mb: float = STATE_BUDGET / 2**20
    """the most the resume state may weigh; Adam's moments are dropped when they do not fit"""
    note: str = ""

    @classmethod
    def read(cls, path: Path) -> CampaignSpec:
        try:
            data = json.loads(path.read_text())
        except (OSError, json.JSONDecodeError) as err:
            raise ValueError(f"{path}: not a readable campaign description ({err})") from None
        known = {f for f in cls.__dataclass_fields__}
        unknown = sorted(set(data) - known)
        if unknown:
            raise ValueError(f"{path}: unknown field(s) {', '.join(unknown)}; fields: {', '.join(sorted(known))}")
        if data.get("val_split") not in (None, "dt", "finish"):  # refused here, not after a stretch of training
            raise ValueError(f"{path}: val_split must be \"dt\", \"finish\" or null, got {data['val_split']!r}")
        try:
            spec = cls(**data)
        except (TypeError, ValueError) as err:
            raise ValueError(f"{path}: {err}") from None
        return spec

    def __post_init__(self) -> None:
        """What a campaign file may say is checked as a file's word, not the user's: its names are
        file-name components, its recipe a list of strings that names no plug-in model (a dotted
        path imports code; train plug-ins with scripts/train.py --model directly)."""
        from agents.pretrained import check_model_file_name

        check_model_file_name(self.name, "campaign name")
        check_model_file_name(self.export, "campaign export")
        if not isinstance(self.train, list) or not all(isinstance(a, str) for a in self.train):
            raise ValueError(f"campaign {self.name}: train must be a list of strings, got {self.train!r}")
        for i, arg in enumerate(self.train):
            flag, eq, value = arg.partition("=")
            if flag == "--model":
                value = value if eq else (self.train[i + 1] if i + 1 < len(self.train) else "")
                if ":" in value:
                    raise ValueError(f"campaign {self.name}: its recipe names the plug-in model {value!r} (a dotted "
                                     "path, whose import runs code); a campaign may only train a registered model")

    def write(self, path: Path) -> None:
        _write_text(path, json.dumps(asdict(self), indent=1) + "\n")

    @property
    def mode(self) -> str | None:
        """How the score runs the network (a curve row's ``mode``; None: one pass per window)."""
        if self.val_split == "finish":
            return "finish"
        return f"split {self.val_split}" if self.val_split else None


def read_json(path: Path, what: str):
    """The JSON in ``path``, or ValueError naming the file and what it is (a file cut short by a
    kill or a full disk, edited by hand): never a raw JSONDecodeError."""
    try:
        return json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
        raise ValueError(f"{path}: not a readable {what} ({err})") from None


def write_json(path: Path, data) -> None:
    """``data`` as indented JSON, written to a temporary and renamed over ``path``."""
    _write_text(path, json.dumps(data, indent=1) + "\n")


def _write_text(path: Path, text: str) -> None:
    write_atomic(path, text)


def _size(payload: dict[str, Any]) -> int:
    from agents.checkpoint import to_safe

    buffer = io.BytesIO()
    torch.save(to_safe(payload), buffer)
    return buffer.tell()


#: the parts of a training checkpoint that hold the episodes in progress (the current windows'
#: observations and info, and the recurrent state carried into the next unroll; the windows'
#: events are reloaded by the envs)
EPISODE_KEYS = ("policy_state", "obs", "info")


def _cast(value: Any, source: torch.dtype, target: torch.dtype) -> Any:
    """``value`` with its ``source``-typed arrays and tensors cast to ``target`` (nested dicts,
    lists and tuples followed; other types unchanged). float32 -> float16 halves the episodes
    in progress; float16 -> float32 restores them."""
    if isinstance(value, torch.Tensor) and value.dtype == source:
        return value.to(target)
    np_source, np_target = (np.dtype(str(d).removeprefix("torch.")) for d in (source, target))
    if isinstance(value, np.ndarray) and value.dtype == np_source:
        return value.astype(np_target)
    if isinstance(value, dict):
        return {k: _cast(v, source, target) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return type(value)(_cast(v, source, target) for v in value)
    return value


def slim_state(payload: dict[str, Any], budget: int = STATE_BUDGET) -> tuple[dict[str, Any], str]:
    """The resume state of a training checkpoint within ``budget`` bytes, and what it gave up,
    one step at a time until it fits:

    - "nothing": the whole checkpoint (a resume continues bitwise);
    - "moments": Adam's moments dropped (the resumed run restarts them and warms its step size up
      again over ``moment_warmup`` steps, see agents.learner);
    - "moments, half episodes": also the episodes in progress (recurrent state, current
      observations and windows) stored as float16, read back as float32;
    - "moments, episodes": the episodes in progress dropped: the resumed run starts fresh episodes
      (the weights, step, schedule and RNG continue).

    The weights stay float32. ValueError when even the last is over budget."""
    if _size(payload) <= budget:
        return payload, "nothing"
    optimizer = dict(payload["optimizer"])
    optimizer["state"] = {}
    slim = {**payload, "optimizer": optimizer}
    if _size(slim) <= budget:
        return slim, "moments"
    slim = {**slim, **{k: _cast(slim.get(k), torch.float32, torch.float16) for k in EPISODE_KEYS}, "episodes_halved": True}
    if _size(slim) <= budget:
        return slim, "moments, half episodes"
    slim = {k: v for k, v in slim.items() if k not in (*EPISODE_KEYS, "env_states", "episodes_halved")}
    size = _size(slim)
    if size > budget:
        raise ValueError(f"the campaign's resume state weighs {size / 2**20:.1f} MB without Adam's moments and "
                         f"episodes, over the budget of {budget / 2**20:.0f} MB: a smaller network, or a larger "
                         "budget (campaign.py new --state-budget-mb)")
    return slim, "moments, episodes"


def unslim_state(payload: dict[str, Any]) -> dict[str, Any]:
    """A training checkpoint from a slim state: the halved episodes widened back to float32."""
    payload = {k: v for k, v in payload.items() if k != "campaign"}
    if payload.pop("episodes_halved", False):
        payload.update({k: _cast(payload.get(k), torch.float16, torch.float32) for k in EPISODE_KEYS})
    return payload


def machine(device: str) -> str:
    """The machine in words, for the curve (no host names)."""
    if torch.device(device).type == "cuda" and torch.cuda.is_available():
        return f"cuda: {torch.cuda.get_device_name(torch.device(device))}"
    return f"cpu: {os.cpu_count()} cores {platform.machine()}"


class Campaign:
    """The files of one campaign: its committed folder and its working folder."""

    def __init__(self, name: str, root: Path | None = None, runs: Path | None = None) -> None:
        if not name or "/" in name or name.startswith("."):
            raise ValueError(f"campaign name {name!r}: a plain folder name is expected")
        self.name = name
        if root is None:  # the committed folder is the checkout's, never an installed package's
            from agents.pretrained import check_writable_checkout

            check_writable_checkout(f"campaign {name}")
        self.dir = Path(root or CAMPAIGNS_DIR) / name
        self.work = Path(runs or Path("runs") / "campaigns") / name
        self.checkpoint = self.work / "train" / "checkpoint.pt"

    @property
    def spec_path(self) -> Path:
        return self.dir / "campaign.json"

    @property
    def state_path(self) -> Path:
        return self.dir / "state.pt"

    @property
    def curve_path(self) -> Path:
        return self.dir / "curve.jsonl"

    @property
    def reference_path(self) -> Path:
        return self.dir / "reference.json"

    def spec(self) -> CampaignSpec:
        if not self.spec_path.exists():
            known = sorted(p.name for p in self.dir.parent.glob("*/campaign.json")) if self.dir.parent.is_dir() else []
            raise FileNotFoundError(f"no campaign {self.name!r} ({self.spec_path} missing); known: "
                                    f"{', '.join(p.split('/')[0] for p in known) or 'none'}; create one with "
                                    f"scripts/campaign.py new")
        return CampaignSpec.read(self.spec_path)

    def curve(self) -> list[dict]:
        if not self.curve_path.exists():
            return []
        rows = []
        for line in self.curve_path.read_text().splitlines():
            try:
                rows.append(json.loads(line))
            except json.JSONDecodeError:  # a line cut by a kill
                continue
        return rows

    def append_curve(self, row: dict) -> None:
        rows = self.curve() + [row]
        _write_text(self.curve_path, "".join(json.dumps(r) + "\n" for r in rows))

    def best(self, mode: str | None = None) -> dict | None:
        """The curve's best row among those scored in ``mode`` (a row's ``mode``; None: one pass):
        scores of different modes are not compared."""
        rows = [r for r in self.curve() if r.get("score") is not None and r.get("mode") == mode]
        return min(rows, key=lambda r: r["score"]) if rows else None

    def state_step(self) -> int | None:
        """The step of the committed state (None: the campaign has not started)."""
        return int(load_checkpoint(self.state_path)["step"]) if self.state_path.exists() else None

    def write_state(self, checkpoint: Path, progress: dict, budget: int = STATE_BUDGET) -> tuple[int, str]:
        """The working checkpoint, slimmed to ``budget`` bytes, as the committed state (atomic);
        ``progress`` (the campaign's wall time, stretches) travels with it. Returns (bytes, what
        the slim state gave up: see :func:`slim_state`)."""
        slim, dropped = slim_state({**load_checkpoint(checkpoint), "campaign": progress}, budget)
        save_checkpoint(self.state_path, slim)
        return self.state_path.stat().st_size, dropped

    def progress(self) -> dict:
        """The campaign's own counters from its state: training hours and stretches so far."""
        if not self.state_path.exists():
            return {"wall_s": 0.0, "stretches": 0}
        return dict(load_checkpoint(self.state_path).get("campaign") or {"wall_s": 0.0, "stretches": 0})

    def restore_working_checkpoint(self) -> str:
        """Make ``runs/campaigns/NAME/train/checkpoint.pt`` the furthest of the working checkpoint
        and the committed state; returns which one it is ('working', 'state' or 'fresh')."""
        state_step = self.state_step()
        if self.checkpoint.exists():
            working_step = int(load_checkpoint(self.checkpoint)["step"])
            if state_step is None or working_step >= state_step:
                return "working"
        if state_step is None:
            return "fresh"
        save_checkpoint(self.checkpoint, unslim_state(load_checkpoint(self.state_path)))
        return "state"


def plot_curve(rows: list[dict], path: Path, title: str) -> Path | None:
    """validation score and AEE per dt against step (and hours) as a PNG; None without matplotlib."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return None
    rows = [r for r in rows if r.get("score") is not None]
    fig, axes = plt.subplots(1, 2, figsize=(10, 3.6))
    steps = [r["step"] for r in rows]
    modes = list(dict.fromkeys(r.get("mode") for r in rows))  # scores of different modes: separate lines
    for mode, style in zip(modes, ("o-", "s--", "^-.", "v:")):
        part = [r for r in rows if r.get("mode") == mode]
        label = "one pass" if mode is None else mode
        axes[0].plot([r["step"] for r in part], [r["score"] for r in part], style, color="k", label=f"score, {label}")
        for key in sorted({k for r in part for k in r.get("aee", {})}):
            axes[1].plot([r["step"] for r in part], [r["aee"].get(key) for r in part], style,
                         label=f"model {key}, {label}")
    axes[0].axhline(1.0, color="grey", lw=0.8, ls="--")
    axes[0].set_xlabel("optimizer step")
    axes[0].set_ylabel("AEE / reference AEE (mean over dt)")
    axes[0].legend(fontsize=7)
    for key in sorted({k for r in rows for k in r.get("aee", {})}):
        axes[1].plot(steps, [r.get("reference_aee", {}).get(key) for r in rows], ":", label=f"reference {key}")
    axes[1].set_xlabel("optimizer step")
    axes[1].set_ylabel("mean AEE (px)")
    axes[1].legend(fontsize=7)
    for r0, r1 in zip(rows, rows[1:]):  # resumes: a new stretch starts
        if r1.get("stretch") != r0.get("stretch"):
            for ax in axes:
                ax.axvline(r1["step"], color="tab:red", lw=0.6, alpha=0.5)
    fig.suptitle(title + " (red lines: resumes)", fontsize=9)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = temporary_path(path)
    fig.savefig(tmp, dpi=90, format="png")
    plt.close(fig)
    os.replace(tmp, path)
    return path
