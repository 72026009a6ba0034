"""The paper's ablations (its Tables 2-4) with the project's recipe, one budget for all.

Every configuration is trained the same way through ``scripts/train.py``:

1. **teacher**: distil per-window contrast-maximisation targets, solved once for the training
   split (``agents/teacher.py``), into the network from scratch (``--loss teacher
   --teacher-cache``); the targets minimise the configuration's loss (L_HMC, or L_AT: the same
   solver with lambda_1 = 0);
2. **fine-tune** (only with ``Budget.finetune_steps`` > 0; none in the documented budget since
   2026-12-04, when it took the full model back to zero flow's devval AEE): the configuration's
   loss itself (``--loss hmc`` or ``--loss at``) from the teacher stage's weights.

Then each is evaluated on the same splits and window lengths (AEE, outliers, cosine, L_HMC,
FWL, RSAT), and its cost measured (parameters, arithmetic and time per window). A finished
configuration's row is appended at once to ``RECORD/rows.jsonl`` (``RECORD`` defaults to ``OUT``;
``scripts/ablations.py`` keeps it in the repository, ``docs/ablations``; committing it is the
user's step, e.g. ``python tools/campaign_commit.py --ablations``, so that finished rows outlive
the machine); the Markdown tables and the validation curves are regenerated there from those
rows after every row.

Resumable: a (configuration, seed) with a row is skipped; a stage with a checkpoint but no
``done.json`` continues from it (``--resume``); an evaluation keeps its finished parts. A stage
that returns before its budget (SIGTERM / Ctrl-C: train.py saves and returns) stops the runner,
so the same command continues later. One runner per output folder (a lock file says so).

Like a campaign (``evflow_cli/campaign.py``), a stage outlives its machine: when it stops, and when
it finishes before its configuration's row is written, its checkpoint is slimmed to the campaign
budget (Adam's moments dropped, restarted with a warm-up on resume) and kept in the record,
``RECORD/unfinished/<configuration>-s<seed>-<stage>.pt``, with its validation lines; a fresh
clone whose run folder lacks the stage continues from it. The row, once written, replaces them.

Seeds: the full model runs every seed given (3); another configuration runs the first seed, and
the second too where its primary number (devval AEE at dt = 1, the first split and window
length evaluated) differs from the full model's mean by at most two of the full model's
sample standard deviations (:func:`needs_second_seed`).
"""

from __future__ import annotations

import dataclasses
import datetime
import fcntl
import json
import math
import os
import re
import statistics
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Literal

import numpy as np
import torch

from agents.checkpoint import load_checkpoint, load_model, save_checkpoint
from agents.evaluation import evaluate, results_json
from agents.policy import RecurrentPolicy
from agents.teacher import TeacherSettings, TeacherTargets, compute_teacher_targets, copy_targets
from envs.atomic import same_file

from .campaign import STATE_BUDGET, slim_state, unslim_state
from .summary import count_parameters, forward_flops, forward_latency_ms

__all__ = ["Configuration", "CONFIGURATIONS", "Budget", "AblationRunner", "needs_second_seed", "render_tables",
           "read_rows", "plot_validation_curves", "PAPER_MVSEC_DT1"]

Loss = Literal["hmc", "at"]
LOSSES: tuple[str, ...] = ("hmc", "at")

#: The paper's MVSEC dt = 1 AEE (outdoor_day1, indoor_flying1, 2, 3) (docs/method.md, "Metrics").
PAPER_MVSEC_DT1: dict[str, tuple[float, float, float, float]] = {
    "mgr-hmc": (0.28, 0.41, 0.70, 0.59),
    "mgr-no-st": (0.32, 0.45, 0.80, 0.67),
    "mgr-no-prior": (0.30, 0.41, 0.78, 0.63),
    "mgr-at": (0.37, 0.52, 0.96, 0.79),
    "convgru-at": (0.47, 0.60, 1.17, 0.93),
}


@dataclass(frozen=True)
class Configuration:
    """One row of the tables: a network (registry name + switches) and the loss it learns."""

    name: str  # short key: run folders, rows, --only
    label: str  # the table's wording
    model: str  # registry name
    loss: Loss  # the teacher's loss and the fine-tuning loss
    model_kwargs: dict = field(default_factory=dict)
    tables: tuple[int, ...] = ()  # the paper tables (2, 3, 4) it appears in

    def __post_init__(self) -> None:
        if self.loss not in LOSSES:
            raise ValueError(f"Configuration.loss must be one of {LOSSES}, got {self.loss!r}")


FULL = "mgr-hmc"
CONFIGURATIONS: dict[str, Configuration] = {c.name: c for c in [
    Configuration(FULL, "EV-MGRFlowNet, L_HMC", "ev-mgrflownet", "hmc", tables=(2, 3)),
    Configuration("mgr-no-st", "without ST-ConvGRU (plain ConvGRU), L_HMC", "ev-mgrflownet", "hmc",
                  {"use_st_convgru": False}, tables=(2,)),
    Configuration("mgr-no-prior", "without prior flows, L_HMC", "ev-mgrflownet", "hmc",
                  {"use_prior_flow": False}, tables=(2,)),
    Configuration("mgr-no-both", "without both, L_HMC", "ev-mgrflownet", "hmc",
                  {"use_st_convgru": False, "use_prior_flow": False}, tables=(2,)),
    Configuration("mgr-at", "EV-MGRFlowNet, L_AT", "ev-mgrflownet", "at", tables=(3,)),
    Configuration("convgru-hmc", "ConvGRU-EV-FlowNet, L_HMC", "convgru-ev-flownet", "hmc", tables=(3, 4)),
    Configuration("convgru-at", "ConvGRU-EV-FlowNet, L_AT", "convgru-ev-flownet", "at", tables=(3, 4)),
    Configuration("xlif-hmc", "XLIF-EV-FlowNet, L_HMC", "xlif-ev-flownet", "hmc", tables=(3,)),
    Configuration("xlif-at", "XLIF-EV-FlowNet, L_AT", "xlif-ev-flownet", "at", tables=(3,)),
    Configuration("evflownet-hmc", "EV-FlowNet (no recurrence), L_HMC", "ev-flownet", "hmc", tables=(3,)),
]}


@dataclass(frozen=True)
class Budget:
    """What every configuration gets: the same data, crops, window lengths, steps and evaluation.

    The defaults are the documented budget (docs/ablations/README.md); the stage options are
    those of the recipe in ``scripts/main.py`` (CACHED_RECIPE, HMC_STAGE), with the teacher
    stage's step size decaying to 0 over its steps so that a fixed step count ends converged.
    """

    teacher_steps: int = 6000
    """Adam steps of the teacher stage (EV-MGRFlowNet on the 2-core CPUs measured: 0.9 steps/s at
    two threads on 2026-12-02's machine, 2.1 at one thread on 2026-12-04's: 48 minutes to 1.9 hours)."""
    finetune_steps: int = 0
    """Adam steps of a fine-tuning stage on the configuration's own loss (0: none). None since
    2026-12-04: 1500 steps of L_HMC took the full model's devval validation AEE from 0.83x zero
    flow's back to 1.00x (docs/ablations/two-stage/), so the configurations' losses enter through
    the teacher targets they define, as in the shipped models' recipe."""
    train_data: str = "synthetic-train"
    """Training split (its teacher targets are solved once per loss)."""
    val_data: str = "../shared/devval"
    """Validation data of the curves (train.py --val-data; '' for none): the independent set, on
    which the shipped models are chosen (docs/ablations/README.md: on ``synthetic-dr-val`` the
    default itself is only 11 % below zero flow, too close for a curve to say anything)."""
    val_every: int = 500
    val_windows: int = 15
    """Windows per validation sequence (15: about 20 s per validation on the busy 2-core CPU)."""
    eval_splits: tuple[str, ...] = ("../shared/devval", "synthetic-test", "synthetic-stress")
    """The first is the compass: the tables' quality columns and the second-seed rule read it."""
    eval_dts: tuple[int, ...] = (1, 4)
    """Window lengths evaluated, in ground-truth frames."""
    eval_windows: int | None = None
    """Windows per evaluated sequence (None: all)."""
    width: str | int = "cpu"
    crop: int = 64
    """Side of the random training crop (pixels)."""
    num_envs: int = 8
    unroll: int = 4
    teacher_window_sizes: tuple[int, ...] = (1, 2, 3, 4)
    finetune_window_sizes: tuple[int, ...] = (4,)
    teacher_lr: float = 3e-4
    """Peak step size of the teacher stage. 3e-4 since 2026-12-05: at 1e-3 every channel of the
    decoder's first stage died (ReLU never firing) about 575 steps in, cutting the residual module
    and the deepest encoder level off from the flow, in three of the four network ablations
    (``tools/dead_units.py``); the rows of that budget are kept in ``docs/ablations/lr-1e-3/``."""
    finetune_lr: float = 3e-4
    warmup_steps: int = 100
    flow_scaling: float = 32.0
    head_init: float = 0.1
    teacher: TeacherSettings = field(default_factory=TeacherSettings)
    """The contrast-maximisation solve of the targets (lambda_1 is set per loss)."""
    cost_size: tuple[int, int] = (128, 128)
    """Input size (H, W) of the arithmetic and latency columns (synthetic-test's frame)."""

    def common_options(self) -> list[str]:
        return ["--width", str(self.width), "--input", "voxel_grid", "--data", self.train_data,
                "--crop", str(self.crop), str(self.crop), "--random-crop", "--flow-scaling", f"{self.flow_scaling:g}",
                "--num-envs", str(self.num_envs), "--unroll", str(self.unroll)]

    def teacher_options(self, targets: Path | None) -> list[str]:
        """train.py options of stage 1 (main.py's CACHED_RECIPE with a decaying step size)."""
        return [*self.common_options(), "--loss", "teacher", "--teacher-cache", str(targets), "--teacher-pixels", "all",
                "--window-size", *map(str, self.teacher_window_sizes), "--lr", f"{self.teacher_lr:g}",
                "--warmup-steps", str(self.warmup_steps), "--decay", "cosine", "--head-init", f"{self.head_init:g}",
                "--steps", str(self.teacher_steps)]

    def finetune_options(self, loss: Loss, init: Path) -> list[str]:
        """train.py options of stage 2 (main.py's HMC_STAGE, with the configuration's loss)."""
        return [*self.common_options(), "--loss", loss, "--window-size", *map(str, self.finetune_window_sizes),
                "--lr", f"{self.finetune_lr:g}", "--init", str(init), "--steps", str(self.finetune_steps)]

    def describe(self) -> str:
        stages = (f"{self.teacher_steps} teacher steps (Adam, step size {self.teacher_lr:g} after {self.warmup_steps} "
                  "warm-up steps, cosine decay to 0)")
        if self.finetune_steps:
            stages += f" + {self.finetune_steps} fine-tuning steps"
        return (f"{stages}; {self.train_data}, {self.crop}x{self.crop} random crops, B = {self.num_envs}, "
                f"L = {self.unroll}, voxel-grid input, width {self.width}, flow scaling {self.flow_scaling:g}")


def needs_second_seed(values: list[float], full_values: list[float]) -> bool:
    """Whether a configuration needs another seed: its mean is within two of the full model's
    sample standard deviations of the full model's mean (the difference is not yet clear).
    values / full_values: the primary number (lower is better) of each finished seed."""
    if len(values) >= 2 or not values:
        return False
    if len(full_values) < 2:
        raise ValueError("needs_second_seed: the full model needs at least 2 seeds for a spread")
    spread = statistics.stdev(full_values)
    return abs(statistics.mean(values) - statistics.mean(full_values)) <= 2 * spread


def read_rows(path: Path) -> list[dict]:
    """The rows of ``rows.jsonl`` (one per finished configuration and seed; a later row of the
    same configuration and seed replaces an earlier one; a line cut by a kill is skipped)."""
    if not path.exists():
        return []
    rows: dict[tuple[str, int], dict] = {}
    for line in path.read_text().splitlines():
        try:
            row = json.loads(line)
        except json.JSONDecodeError:
            continue
        rows[(row["config"], int(row["seed"]))] = row
    return list(rows.values())


def _write_json(path: Path, payload) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(payload, indent=1, default=str) + "\n")
    os.replace(tmp, path)


def cache_name(split: str) -> str:
    """A file name for ``split`` inside a cache folder: a split named by a path
    ("../shared/devval") must not lead out of it. A plain split name is kept; any other gets its
    characters outside ``[A-Za-z0-9_-]`` replaced and a checksum of the whole string, so that two
    paths that differ only there ("a/b", "a_b") do not share a file."""
    if re.fullmatch(r"[A-Za-z0-9_-]+", split):
        return split
    return f"{re.sub(r'[^A-Za-z0-9_-]', '_', split)}-{zlib.crc32(split.encode()):08x}"


def _validation_points(metrics: Path, offset: int) -> list[tuple[int, float, float]]:
    """(step, val AEE of the model, of zero flow) lines of a train.py metrics.jsonl, one per
    step (a validation repeated at the same step, e.g. the last periodic one and the final one,
    counts once)."""
    points: dict[int, tuple[int, float, float]] = {}
    if metrics.exists():
        for line in metrics.read_text().splitlines():
            try:
                row = json.loads(line)
            except json.JSONDecodeError:
                continue
            if "val_aee_model" in row:
                step = offset + int(row["step"])
                points[step] = (step, row["val_aee_model"], row.get("val_aee_zero"))
    return [points[step] for step in sorted(points)]


class RunnerStopped(RuntimeError):
    """A training stage returned before its budget (interrupted): rerun the command to continue."""


class AblationRunner:
    """Trains, evaluates and tabulates the configurations under ``out``.

    train: the training command as a function of its argv (``scripts/train.py``'s ``main``).
    record: the folder of what must outlive the run folder (rows.jsonl, budget.json, tables.md,
    curves/, targets/); default ``out``. on_row: called with the files written after each
    finished row (e.g. to commit them); on_targets: called with the record's copy of teacher
    targets solved here; on_state: called with a stage's slim state kept in the record.
    """

    def __init__(self, out: str | os.PathLike, budget: Budget, train: Callable[[list[str]], object], *,
                 seeds: tuple[int, ...] = (0, 1, 2), only: list[str] | None = None, device: str = "cpu",
                 targets: dict[str, str] | None = None, log: Callable[[str], None] = print,
                 record: str | os.PathLike | None = None,
                 on_row: Callable[[list[Path]], None] | None = None,
                 on_targets: Callable[[list[Path]], None] | None = None,
                 on_state: Callable[[list[Path]], None] | None = None) -> None:
        unknown = sorted(set(only or []) - set(CONFIGURATIONS))
        if unknown:
            raise ValueError(f"unknown configuration(s) {unknown}; known: {list(CONFIGURATIONS)}")
        if not seeds:
            raise ValueError("seeds: at least one")
        self.out = Path(out)
        self.budget = budget
        self.train = train
        self.seeds = tuple(seeds)
        self.names = [name for name in CONFIGURATIONS if only is None or name in only]
        self.device = device
        self.given_targets = dict(targets or {})
        self.log = log
        self.record = Path(record) if record is not None else self.out
        self.rows_path = self.record / "rows.jsonl"
        self.on_row = on_row
        self.on_targets = on_targets
        self.on_state = on_state

    # -- the plan ------------------------------------------------------------------------------

    def run(self, report: Path | None = None) -> list[dict]:
        """Run every (configuration, seed) still missing, in this order: the full model's first
        seed, every other configuration's first seed, the full model's other seeds, then second
        seeds where :func:`needs_second_seed` says so. Returns the rows."""
        self.out.mkdir(parents=True, exist_ok=True)
        with open(self.out / "runner.lock", "a") as lock:  # the lock goes with the process, however it ends
            try:
                fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                raise RuntimeError(f"{self.out}: another ablation runner is working here (runner.lock)") from None
            lock.truncate(0)
            lock.write(f"{os.getpid()}\n")
            lock.flush()
            self._check_budget()
            others = [name for name in self.names if name != FULL]
            full = [FULL] if FULL in self.names else []
            for name, seed in [(n, self.seeds[0]) for n in full + others] + [(FULL, s) for s in self.seeds[1:] if full]:
                self._ensure(name, seed, report)
            if len(self.seeds) > 1 and full:
                for name in others:
                    if needs_second_seed(self._primary(name), self._primary(FULL)):
                        self._ensure(name, self.seeds[1], report)
        return read_rows(self.rows_path)

    def _check_budget(self) -> None:
        """Record the budget in OUT/budget.json; a folder holding runs at another budget is
        refused (its rows would count as finished), naming the fields that differ."""
        path = self.record / "budget.json"
        budget = json.loads(json.dumps(dataclasses.asdict(self.budget), default=str))
        if path.exists():
            stored = json.loads(path.read_text())
            differ = sorted(k for k in set(stored) | set(budget) if stored.get(k) != budget.get(k))
            if differ:
                raise ValueError(f"{self.out}: holds runs at another budget (differs in {', '.join(differ)}); "
                                 "use another output folder")
        else:
            _write_json(path, budget)

    def _primary(self, name: str) -> list[float]:
        split, dt = self.budget.eval_splits[0], f"dt{self.budget.eval_dts[0]}"
        return [row["eval"][split][dt]["aee"] for row in read_rows(self.rows_path) if row["config"] == name]

    def _ensure(self, name: str, seed: int, report: Path | None) -> None:
        if any(r["config"] == name and r["seed"] == seed for r in read_rows(self.rows_path)):
            return
        row = self.run_one(CONFIGURATIONS[name], seed)
        with open(self.rows_path, "a") as f:
            f.write(json.dumps(row, default=str) + "\n")
            f.flush()
            os.fsync(f.fileno())
        for stage in ("teacher", "finetune"):  # the row holds what they were kept for
            self.kept_state(self.out / f"{name}-s{seed}" / stage).unlink(missing_ok=True)
        split, dt = self.budget.eval_splits[0], f"dt{self.budget.eval_dts[0]}"
        self.log(f"[ablations] {name} seed {seed}: done, {split} {dt} AEE {row['eval'][split][dt]['aee']}")
        self.write_outputs(report)
        if self.on_row is not None:
            written = [self.rows_path, self.record / "budget.json", self.record / "tables.md",
                       *sorted((self.record / "curves").glob("*.png"))]
            self.on_row(written + ([report] if report is not None else []))

    def write_outputs(self, report: Path | None = None) -> str:
        """Regenerate OUT/tables.md, the validation curves and, with ``report``, the tables in it."""
        rows = read_rows(self.rows_path)
        zero = self.zero_flow()
        text = render_tables(rows, zero, self.budget, self.seeds)
        self.record.mkdir(parents=True, exist_ok=True)
        (self.record / "tables.md").write_text(text + "\n")
        for name in {r["config"] for r in rows}:
            plot_validation_curves([r for r in rows if r["config"] == name], self.record / "curves" / f"{name}.png")
        if report is not None:
            write_report(report, text)
        return text

    # -- one configuration ---------------------------------------------------------------------

    def targets(self, loss: Loss) -> Path:
        """The teacher targets of ``loss`` on the training split, solved once (resumable).

        A file given for ``loss`` is used as it is (solved into that path if missing). Otherwise
        ``OUT/targets/<loss>.h5`` if there, else the record's copy ``RECORD/targets/<loss>.h5`` (a
        new machine need not solve them again: about an hour per loss on the 2-core CPU), else
        they are solved into OUT. Whatever file is used is checked against the budget's solver
        settings. Targets in OUT that the record lacks (just solved, or solved before the record
        kept them) are copied there (float16, compressed) and handed to ``on_targets``."""
        settings = dataclasses.replace(self.budget.teacher, lambda_1=1.0 if loss == "hmc" else 0.0)
        given = self.given_targets.get(loss)
        if given:
            path = Path(given)
            if path.exists():
                self._check_targets(path, loss, settings)
                return path
            return self._solve(loss, settings, path)
        path, kept = self.out / "targets" / f"{loss}.h5", self.record_targets(loss)
        if not path.exists() and kept.exists():
            self._check_targets(kept, loss, settings)
            return kept
        if path.exists():
            self._check_targets(path, loss, settings)
        else:
            self._solve(loss, settings, path)
        if not kept.exists() and not same_file(kept, path):
            copy_targets(path, kept, dtype=np.float16)  # under 5 MB for a repository; ~0.016 px at 32 px
            if self.on_targets is not None:
                self.on_targets([kept])
        return path

    def _solve(self, loss: Loss, settings: TeacherSettings, path: Path) -> Path:
        self.log(f"[ablations] solving the {loss} teacher's targets of {self.budget.train_data} into {path}")
        return compute_teacher_targets(self.budget.train_data, path, window_sizes=self.budget.teacher_window_sizes,
                                       settings=settings, device=self.device)

    def record_targets(self, loss: Loss) -> Path:
        """Where the record keeps the targets of ``loss``."""
        return self.record / "targets" / f"{loss}.h5"

    def _check_targets(self, path: Path, loss: Loss, settings: TeacherSettings) -> None:
        stored = TeacherTargets(path).config
        wanted = json.loads(json.dumps({"data": self.budget.train_data, **settings.describe()}))
        differ = {key for key in wanted if stored.get(key) != wanted[key]}
        if float(stored.get("evidence_prior", 0.0)) != float(settings.evidence_prior):  # 0 is not recorded
            differ.add("evidence_prior")
        if not set(self.budget.teacher_window_sizes) <= set(stored.get("window_sizes", [])):
            differ.add("window_sizes")
        found = [f"{key}={stored.get(key)!r}" for key in sorted(differ)]
        found += [f"{key} (not solved with one setting)" for key in ("derived", "merged_from") if key in stored]
        if found:
            raise ValueError(f"{path}: not the {loss} teacher's targets this budget asks for (differs in "
                             f"{', '.join(found)})")

    def kept_state(self, folder: Path) -> Path:
        """Where the record keeps the slim state of the stage trained in ``folder``
        (``OUT/<configuration>-s<seed>/<stage>``)."""
        return self.record / "unfinished" / f"{folder.parent.name}-{folder.name}.pt"

    def _keep_stage(self, folder: Path, done: bool) -> None:
        """The stage's checkpoint, slimmed, and its metrics' validation lines, into the record."""
        payload = load_checkpoint(folder / "checkpoint.pt")
        slim, dropped = slim_state(payload, STATE_BUDGET)
        lines = []
        if (folder / "metrics.jsonl").exists():
            lines = [line for line in (folder / "metrics.jsonl").read_text().splitlines()
                     if line.strip() and any(k.startswith("val_") for k in json.loads(line))]
        path = self.kept_state(folder)
        path.parent.mkdir(parents=True, exist_ok=True)
        save_checkpoint(path, {**slim, "ablation": {"validation_lines": lines, "done": done}})
        self.log(f"[ablations] {folder}: state at step {payload['step']} kept in {path} "
                 f"({path.stat().st_size / 2**20:.1f} MB; left out: {dropped})")
        if self.on_state is not None:
            self.on_state([path])

    def _restore_stage(self, folder: Path) -> None:
        """A stage missing from the run folder (a fresh clone) continued from the record's state."""
        kept = self.kept_state(folder)
        if (folder / "checkpoint.pt").exists() or (folder / "done.json").exists() or not kept.exists():
            return
        payload = load_checkpoint(kept)
        carried = payload.pop("ablation", None) or {}
        folder.mkdir(parents=True, exist_ok=True)
        (folder / "metrics.jsonl").write_text("".join(line + "\n" for line in carried.get("validation_lines", [])))
        save_checkpoint(folder / "checkpoint.pt", unslim_state(payload))
        if carried.get("done"):
            _write_json(folder / "done.json", {"step": int(payload["step"]), "restored_from": str(kept)})
        self.log(f"[ablations] {folder}: continued from the record's state at step {payload['step']} ({kept})")

    def _stage(self, folder: Path, options: list[str], steps: int, seed: int) -> Path:
        """Run (or continue, or skip) one training stage; returns its checkpoint."""
        checkpoint = folder / "checkpoint.pt"
        self._restore_stage(folder)
        if (folder / "done.json").exists():
            return checkpoint
        run = ["--out", str(folder), "--no-progress", "--device", self.device, "--ckpt-every", "100"]
        if self.budget.val_data:
            run += ["--val-data", self.budget.val_data, "--val-every", str(self.budget.val_every),
                    "--val-windows", str(self.budget.val_windows)]
        else:
            run += ["--val-data", ""]
        if checkpoint.exists():
            self.log(f"[ablations] {folder}: resuming from step {load_checkpoint(checkpoint)['step']}")
            self.train(["--resume", *run])
        else:
            (folder / "metrics.jsonl").unlink(missing_ok=True)  # killed before its first checkpoint
            self.log(f"[ablations] {folder}: training {steps} steps")
            self.train([*options, "--seed", str(seed), *run])
        step = load_checkpoint(checkpoint)["step"] if checkpoint.exists() else 0
        if checkpoint.exists():
            self._keep_stage(folder, done=step >= steps)
        if step < steps:
            raise RunnerStopped(f"{folder}: stopped at step {step} of {steps}; rerun the command to continue")
        _write_json(folder / "done.json", {"step": step, "date": datetime.datetime.now().isoformat(timespec="seconds")})
        return checkpoint

    def run_one(self, config: Configuration, seed: int) -> dict:
        """Train (both stages), evaluate and measure one configuration; returns its row."""
        folder = self.out / f"{config.name}-s{seed}"
        model_options = ["--model", config.model]
        for key, value in config.model_kwargs.items():
            model_options += ["--model-kwarg", f"{key}={json.dumps(value)}"]
        b = self.budget
        teacher = folder / "teacher"
        self._restore_stage(teacher)  # a fresh clone: the stage as the record keeps it
        targets = None if (teacher / "done.json").exists() else self.targets(config.loss)  # not needed once done
        checkpoint = self._stage(teacher, [*model_options, *b.teacher_options(targets)], b.teacher_steps, seed)
        if b.finetune_steps:
            checkpoint = self._stage(folder / "finetune", [*model_options, *b.finetune_options(config.loss, checkpoint)],
                                     b.finetune_steps, seed)
        model, payload = load_model(checkpoint, map_location=self.device)
        cfg = payload.get("config") or {}
        policy = RecurrentPolicy(model, device=self.device, input_key=cfg.get("input", "voxel_grid"),
                                 voxel_bins=cfg.get("voxel_bins", 5))
        evaluated = self._evaluate(folder / "eval", policy)
        height, width = b.cost_size
        return {
            "config": config.name, "label": config.label, "seed": seed, "model": config.model,
            "model_kwargs": config.model_kwargs, "loss": config.loss,
            "steps": {"teacher": b.teacher_steps, "finetune": b.finetune_steps},
            "eval": evaluated,
            "parameters": count_parameters(model),
            "gflop_per_window": forward_flops(model.cpu(), 1, height, width) / 1e9,
            "latency_ms": forward_latency_ms(model, height, width, device=self.device),
            "latency_threads": torch.get_num_threads(),
            "validation": [list(p) for p in self.validation_curve(folder)],
            "date": datetime.date.today().isoformat(),
        }

    def validation_curve(self, folder: Path) -> list[tuple[int, float, float]]:
        """(step over both stages, val AEE, zero flow's val AEE) of one run."""
        points = _validation_points(folder / "teacher" / "metrics.jsonl", 0)
        return points + _validation_points(folder / "finetune" / "metrics.jsonl", self.budget.teacher_steps)

    def _evaluate(self, folder: Path, policy) -> dict:
        """{split: {"dtK": pooled metrics}}; each split and window length cached in ``folder``."""
        out: dict = {}
        for split in self.budget.eval_splits:
            for dt in self.budget.eval_dts:
                part = folder / f"{cache_name(split)}-dt{dt}.json"
                if not part.exists():
                    rows = evaluate(policy, split, window="frames", window_size=dt,
                                    max_windows=self.budget.eval_windows, progress=False)
                    _write_json(part, json.loads(results_json({f"dt{dt}": {"model": rows}}))["overall"][f"dt{dt}"])
                out.setdefault(split, {})[f"dt{dt}"] = json.loads(part.read_text())
        return out

    def zero_flow(self) -> dict:
        """Zero flow's metrics on the evaluated splits (computed once, cached)."""
        return self._evaluate(self.out / "zero-flow", None)


# -- tables ------------------------------------------------------------------------------------

START, END = "<!-- ablations:start -->", "<!-- ablations:end -->"


def _cell(values: list[float], digits: int) -> str:
    values = [v for v in values if v is not None and math.isfinite(v)]
    if not values:
        return "-"
    if len(values) == 1:
        return f"{values[0]:.{digits}f}"
    return f"{statistics.mean(values):.{digits}f} ± {statistics.stdev(values):.{digits}f}"


def _paper(name: str) -> str:
    figures = PAPER_MVSEC_DT1.get(name)
    if figures is None:
        return "n/a"
    return f"{sum(figures) / 4:.3f} ({' / '.join(f'{v:.2f}' for v in figures)})"


def _curve_change(row: dict) -> float | None:
    """Change of the val AEE over the last quarter of the steps, % of its earlier value (flat: near 0)."""
    points = row.get("validation") or []
    if len(points) < 2:
        return None
    last_step = points[-1][0]
    earlier = [p for p in points if p[0] <= 0.75 * last_step] or points[:1]
    return 100 * (points[-1][1] - earlier[-1][1]) / earlier[-1][1]


def render_tables(rows: list[dict], zero: dict, budget: Budget, seeds: tuple[int, ...]) -> str:
    """The Markdown block (between the report markers) of the paper's Tables 2-4 layouts."""
    by_name: dict[str, list[dict]] = {}
    for row in sorted(rows, key=lambda r: r["seed"]):
        by_name.setdefault(row["config"], []).append(row)
    splits, dts = budget.eval_splits, [f"dt{k}" for k in budget.eval_dts]

    def metric(name: str, split: str, dt: str, key: str) -> list[float]:
        return [r["eval"][split][dt].get(key) for r in by_name[name]]

    short = _short_split
    accuracy = [(s, d) for s in splits for d in dts]
    head = (["configuration", "seeds"] + [f"AEE {short(s)} {d}" for s, d in accuracy]
            + [f"% out {short(splits[0])} {dts[0]}", f"cos {short(splits[0])} {dts[0]}",
               f"L_HMC {short(splits[0])} {dts[0]}", "val AEE change over the last quarter of steps, %", "parameters",
               f"GFLOP / {budget.cost_size[0]}x{budget.cost_size[1]} window", "ms / window",
               "paper MVSEC dt=1 AEE: mean (outdoor_day1 / indoor_flying1 / 2 / 3)"])

    def pending(name: str, columns: int) -> str:  # not finished yet: the row is there, with the paper's figure
        return "| " + " | ".join([CONFIGURATIONS[name].label, "pending", *["-"] * columns, _paper(name)]) + " |"

    def accuracy_row(name: str) -> str:
        runs = by_name.get(name)
        if not runs:
            return pending(name, len(head) - 3)
        cells = [runs[0]["label"], ", ".join(str(r["seed"]) for r in runs)]
        cells += [_cell(metric(name, s, d, "aee"), 3) for s, d in accuracy]
        cells += [_cell(metric(name, splits[0], dts[0], "outlier_pct"), 1),
                  _cell(metric(name, splits[0], dts[0], "cosine"), 2), _cell(metric(name, splits[0], dts[0], "hmc"), 4),
                  _cell([_curve_change(r) for r in runs], 1), f"{runs[0]['parameters']:,}",
                  f"{runs[0]['gflop_per_window']:.3f}", _cell([r["latency_ms"] for r in runs], 1), _paper(name)]
        return "| " + " | ".join(cells) + " |"

    zero_cells = (["zero flow (reference)", "-"] + [_cell([zero[s][d].get("aee")], 3) for s, d in accuracy]
                  + [_cell([zero[splits[0]][dts[0]].get("outlier_pct")], 1), "-",
                     _cell([zero[splits[0]][dts[0]].get("hmc")], 4), "-", "0", "0", "-", "-"])

    def table(number: int, title: str) -> list[str]:
        names = [n for n, c in CONFIGURATIONS.items() if number in c.tables]
        return [f"**Table {number} layout: {title}**", "", "| " + " | ".join(head) + " |",
                "|---|---|" + "---:|" * (len(head) - 3) + "---|", "| " + " | ".join(zero_cells) + " |",
                *[accuracy_row(n) for n in names], ""]

    lines = [
        START,
        _report_intro(rows, by_name, budget, seeds),
        "",
        *table(2, "network ablations (L_HMC)"),
        *table(3, "losses and baselines"),
        *_quality_table(by_name, splits, dts, pending),
        END,
    ]
    return "\n".join(lines)


def _quality_table(by_name: dict[str, list[dict]], splits: list[str], dts: list[str], pending) -> list[str]:
    """The lines of the Table 4 layout: FWL and RSAT per split and dt (``pending(name, columns)``:
    the row of a configuration not finished yet)."""
    quality = [(s, d, key) for s in splits for d in dts for key in ("fwl", "rsat")]
    table4 = ["**Table 4 layout: FWL (higher is better) and RSAT (lower is better), scored from the events alone "
              "(no ground truth read)**", "",
              "| configuration | seeds | " + " | ".join(f"{k.upper()} {_short_split(s)} {d}" for s, d, k in quality)
              + " | paper MVSEC dt=1 AEE |",
              "|---|---|" + "---:|" * len(quality) + "---|",
              "| zero flow (reference) | - | " + " | ".join("1.0000" for _ in quality) + " | - |"]
    for name in [n for n, c in CONFIGURATIONS.items() if 4 in c.tables]:
        if name not in by_name:
            table4.append(pending(name, len(quality)))
            continue
        runs = by_name[name]
        table4.append(f"| {runs[0]['label']} | {', '.join(str(r['seed']) for r in runs)} | "
                      + " | ".join(_cell([r["eval"][s][d].get(k) for r in runs], 4) for s, d, k in quality)
                      + f" | {_paper(name)} |")
    return table4


def _short_split(split: str) -> str:
    """A split's short name in a column head: "../shared/devval" -> "devval", "synthetic-test" -> "test"."""
    return Path(split).name.replace("synthetic-", "")


def _report_intro(rows: list[dict], by_name: dict[str, list[dict]], budget: Budget, seeds: tuple[int, ...]) -> str:
    """The paragraph above the tables: the budget, the seeds, what was evaluated, the runs finished."""
    splits, dts = budget.eval_splits, [f"dt{k}" for k in budget.eval_dts]
    dates = sorted({r["date"] for r in rows})
    seed_sets = [{r["seed"] for r in group} for group in by_name.values()]
    common = sorted(set.intersection(*seed_sets)) if seed_sets else []
    more = "" if all(len(s) == len(common) for s in seed_sets) else ", more where the seeds column lists them"
    return (
        f"Budget per configuration: {budget.describe()}. "
        + (f"Seeds {', '.join(map(str, common))} for every configuration{more}. " if len(common) > 1 else
           f"Seeds {', '.join(map(str, seeds))} for the full model; the others seed {seeds[0]}, and seed {seeds[1]} "
           f"too where their {_short_split(splits[0])} {dts[0]} AEE is within 2 standard deviations of the full model's. "
           if len(seeds) > 1 else
           f"Seed {seeds[0]} for every configuration so far (the seed column says which rows have more). ")
        + "Mean ± sample standard deviation over seeds. Evaluated on every window"
        + (f" (the first {budget.eval_windows} per sequence)" if budget.eval_windows else "")
        + f" of {', '.join(f'`{s}`' for s in splits)} at their own sensor size. "
        f"Runs finished (configuration x seed): {len(rows)}" + (f", {dates[0]} to {dates[-1]}" if dates else "") + ". "
        "The paper column is MVSEC, another data set: compare orderings, not values. "
        "Validation curves: `curves/<configuration>.png` in the record folder (`docs/ablations` by default).")


def write_report(path: Path, block: str) -> None:
    """Put ``block`` between the markers of ``path`` (appended as a section if it has none)."""
    text = path.read_text() if path.exists() else ""
    if START in text and END in text:
        text = text[: text.index(START)] + block + text[text.index(END) + len(END):]
    else:
        text = text.rstrip() + "\n\n## Ablations (paper Tables 2-4 layout)\n\n" + block + "\n"
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(text)
    os.replace(tmp, path)


# -- validation curves -------------------------------------------------------------------------

def _dashed(draw, start: tuple[float, float], end: tuple[float, float], colour: str, dash: float = 6.0) -> None:
    """A dashed line from ``start`` to ``end`` (pixels)."""
    length = math.hypot(end[0] - start[0], end[1] - start[1])
    for i in range(0, int(length // dash) + 1, 2):
        a, b = i * dash / max(length, 1e-9), min(1.0, (i + 1) * dash / max(length, 1e-9))
        draw.line([start[0] + a * (end[0] - start[0]), start[1] + a * (end[1] - start[1]),
                   start[0] + b * (end[0] - start[0]), start[1] + b * (end[1] - start[1])], fill=colour)


def _curve_range(points: list[tuple]) -> tuple[float, float, float]:
    """The plot's last step and its value range (the val AEE and zero flow's, padded by 5%; at
    least 1 px wide) for (step, val AEE, zero-flow AEE or None) points."""
    x_max = max(p[0] for p in points) or 1
    values = [p[1] for p in points] + [p[2] for p in points if p[2] is not None]
    y_min, y_max = min(values), max(values)
    if y_max - y_min < 1e-9:
        y_min, y_max = y_min - 0.5, y_max + 0.5
    pad = 0.05 * (y_max - y_min)
    return x_max, y_min - pad, y_max + pad


def plot_validation_curves(rows: list[dict], path: Path, size: tuple[int, int] = (640, 400)) -> Path:
    """A PNG of val AEE against step (both stages) for the runs of one configuration, one line
    per seed, zero flow's val AEE dashed, the start of the fine-tuning stage dotted (Pillow)."""
    from PIL import Image, ImageDraw

    width, height = size
    left, right, top, bottom = 60, 20, 46, 40  # the title and, below it, the legend above the box
    image = Image.new("RGB", size, "white")
    draw = ImageDraw.Draw(image)
    curves = [[(p[0], p[1], p[2]) for p in r.get("validation") or []] for r in rows]
    points = [p for c in curves for p in c]
    title = f"{rows[0]['label'] if rows else ''}: validation AEE (px) vs step"
    draw.text((left, 8), title, fill="black")
    if points:
        x_max, y_min, y_max = _curve_range(points)

        def xy(step: float, value: float) -> tuple[float, float]:
            return (left + (width - left - right) * step / x_max,
                    height - bottom - (height - top - bottom) * (value - y_min) / (y_max - y_min))

        draw.rectangle([left, top, width - right, height - bottom], outline="black")
        for i in range(5):
            value = y_min + (y_max - y_min) * i / 4
            _, y = xy(0, value)
            draw.line([left - 4, y, left, y], fill="black")
            draw.text((4, y - 6), f"{value:.3f}", fill="black")
            step = x_max * i / 4
            x, _ = xy(step, y_min)
            draw.line([x, height - bottom, x, height - bottom + 4], fill="black")
            draw.text((x - 12, height - bottom + 8), f"{step:.0f}", fill="black")
        teacher_steps = rows[0].get("steps", {}).get("teacher")
        if teacher_steps and rows[0].get("steps", {}).get("finetune"):
            x, _ = xy(teacher_steps, y_min)
            for y in range(top, height - bottom, 6):
                draw.point((x, y), fill="gray")
            draw.text((x + 3, top + 3), "fine-tuning", fill="gray")
        zero = sorted({(p[0], p[2]) for p in points if p[2] is not None})
        for (s0, z0), (s1, z1) in zip(zero, zero[1:]):
            _dashed(draw, xy(s0, z0), xy(s1, z1), "gray")
        colours = ["#1f77b4", "#d62728", "#2ca02c", "#9467bd"]
        for i, curve in enumerate(curves):
            colour = colours[i % len(colours)]
            line = [xy(s, v) for s, v, _ in curve]
            if len(line) > 1:
                draw.line(line, fill=colour, width=2)
            for x, y in line:
                draw.ellipse([x - 2, y - 2, x + 2, y + 2], fill=colour)
        legend = [(f"seed {row['seed']}", colours[i % len(colours)]) for i, row in enumerate(rows)]
        x = left
        for text, colour in legend + [("zero flow (dashed)", "gray")]:
            draw.text((x, 26), text, fill=colour)
            x += draw.textlength(text) + 16
    else:
        draw.text((left, height // 2), "no validation points", fill="black")
    path.parent.mkdir(parents=True, exist_ok=True)
    image.save(path)
    return path
