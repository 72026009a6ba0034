"""A long training run that survives sessions: train in chunks, validate after each, and ship
(export float16 weights + provenance to agents/weights/NAME) whenever the validation improves.
Nothing here writes to git; ``scripts/campaign.py`` keeps a run's whole state resumable in the
repository.

    python scripts/ship.py --name ev-mgrflownet-cpu-mine --out runs/ship-mine --hours 2 \\
        --init ev-mgrflownet-cpu-synthetic -- <scripts/train.py options of the recipe>

Each chunk is ``scripts/train.py`` for --chunk-minutes (a fresh run the first time, ``--resume``
afterwards). After each chunk the checkpoint is evaluated on --val-data (first --val-windows
windows of every sequence, dt = 1 and 4; the score is the mean over both of the model's AEE as
a ratio to zero flow's); a lower score than the one recorded in agents/weights/NAME.json is
exported there, so a restart on a new machine (no runs/ folder) continues from that model once it
is committed (``--init NAME``).

The validation data must be held out from training and from every test split (the default
``synthetic-dr-val`` is): it picks the model, so it is not a test.
"""

from __future__ import annotations

import argparse
import datetime
import json
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

from agents.options import command_parser, option, options_from_args, positive_float, positive_int

ROOT = Path(__file__).resolve().parents[2]  # the checkout
CODE = ROOT  # the checkout whose train.py / evaluate.py run (--code: a fixed snapshot)


@dataclass(kw_only=True)
class ShipOptions:
    """What scripts/ship.py trains, validates and ships (train.py's options of the recipe follow
    ``--``)."""

    name: str = option(required=True)
    """the shipped model's name (agents/weights/NAME.pt/.json)"""
    out: str = option(required=True)
    """run folder (train/ checkpoint, val/ evaluations, ship.jsonl)"""
    init: str | None = None
    """weights to start from the first time (checkpoint or shipped name)"""
    hours: float = option(1.0, type=positive_float)
    """stop after this long (a chunk in progress finishes)"""
    chunk_minutes: float = option(10.0, type=positive_float)
    """training between validations"""
    val_data: str = "synthetic-dr-val"
    """held-out validation data (never a training or test split: it picks the model)"""
    val_windows: int = option(8, type=positive_int)
    """windows per validation sequence"""
    val_split: str | None = option(None, metavar="N|dt")
    """validate the model stepped through sub-windows (scripts/evaluate.py --split), e.g. dt"""
    note: str = ""
    """what the run is, for the provenance"""
    weights_dir: str | None = None
    """where to ship (default: agents/weights of this checkout)"""
    code: str | None = None
    """run training and validation from this checkout (e.g. a git worktree of a fixed commit, so edits to this one cannot disturb a long run); weights are still shipped into this one"""


def build_parser() -> argparse.ArgumentParser:
    return command_parser(ShipOptions, __doc__)


def validation_score(checkpoint: Path, data: str, windows: int, out: Path, split: str | None = None) -> tuple[float, dict]:
    """Mean over dt = 1 and 4 of (model AEE / zero flow AEE) on ``data``, and the evaluation JSON.
    split: score the model as ``scripts/evaluate.py --split`` runs it (e.g. "dt": one network step
    per ground-truth interval) instead of one step per window."""
    out.mkdir(parents=True, exist_ok=True)
    cmd = [sys.executable, str(CODE / "scripts" / "evaluate.py"), "--checkpoint", str(checkpoint), "--name", "model",
           "--zero", "--data", data, "--dt", "1", "4", "--max-windows", str(windows), "--pictures", "0",
           "--no-progress", "--out", str(out), "--overwrite", *(["--split", split] if split else [])]  # its own folder
    # --dt: --window-size's other name, which the evaluate.py of an older --code snapshot also knows
    subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL)
    results = json.loads((out / "results.json").read_text())
    row = results if not split else results["baselines"][f"model + split {split}"]
    ratios = []
    for key in ("dt1", "dt4"):
        model, zero = row["overall"][key]["aee"], results["baselines"]["zero flow"]["overall"][key]["aee"]
        ratios.append(model / zero)
    return sum(ratios) / len(ratios), results


def shipped_score(name: str, weights_dir: Path) -> float:
    meta = weights_dir / f"{name}.json"
    if not meta.exists():
        return float("inf")
    return float(json.loads(meta.read_text()).get("validation", {}).get("score", float("inf")))


def main(argv=None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    cut = argv.index("--") if "--" in argv else len(argv)
    args = options_from_args(ShipOptions, build_parser().parse_args(argv[:cut]))
    global CODE
    CODE = Path(args.code).resolve() if args.code else ROOT
    sys.path.insert(0, str(CODE))
    weights_dir = Path(args.weights_dir) if args.weights_dir else ROOT / "agents" / "weights"
    recipe = argv[cut + 1 :]
    out = Path(args.out)
    train_dir = out / "train"
    checkpoint = train_dir / "checkpoint.pt"
    log = out / "ship.jsonl"
    out.mkdir(parents=True, exist_ok=True)
    deadline = time.time() + 3600 * args.hours
    chunk = len(log.read_text().splitlines()) if log.exists() else 0  # continues the numbering of a restart
    while time.time() < deadline:
        minutes = str(min(args.chunk_minutes, max(0.5, (deadline - time.time()) / 60)))
        if checkpoint.exists():
            cmd = ["--resume", "--out", str(train_dir), "--minutes", minutes]
        else:
            # a fresh machine: continue from the committed model when there is one
            init = args.init
            if (weights_dir / f"{args.name}.pt").exists():
                init = str(weights_dir / f"{args.name}.pt")
            cmd = [*recipe, "--out", str(train_dir), "--minutes", minutes, "--val-data", "", "--overwrite",
                   *(["--init", init] if init else [])]  # (--overwrite: metrics of a chunk killed before its first save)
        print(f"[ship] chunk {chunk}: train.py {' '.join(cmd)}", flush=True)
        subprocess.run([sys.executable, str(CODE / "scripts" / "train.py"), *cmd, "--no-progress"], check=True)
        score, results = validation_score(checkpoint, args.val_data, args.val_windows, out / "val" / f"chunk{chunk}",
                                          split=args.val_split)
        best = shipped_score(args.name, weights_dir)
        record = {"chunk": chunk, "score": score, "best_before": best, "time": datetime.datetime.now().isoformat()}
        print(f"[ship] validation score {score:.4f} (shipped: {best:.4f})", flush=True)
        if score < best:
            from agents.checkpoint import load_checkpoint
            from agents.pretrained import export_pretrained

            steps = load_checkpoint(checkpoint).get("step")
            provenance = {
                # the snapshot's location is this machine's business, not the provenance's
                "command": "python scripts/ship.py " + " ".join(
                    "SNAPSHOT" if args.code and a == args.code else a for a in argv),
                "date": datetime.date.today().isoformat(),
                "note": args.note,
                "validation": {"data": args.val_data, "windows_per_sequence": args.val_windows, "score": score,
                               "definition": "mean over dt = 1 and 4 of AEE / zero flow's AEE"
                               + (f", the network stepped through sub-windows (--split {args.val_split})"
                                  if args.val_split else ""), "step": steps},
                "evaluation": results,
            }
            export_pretrained(checkpoint, args.name, provenance, directory=weights_dir, overwrite=True)  # improves its own
            record["shipped"] = True
        with log.open("a") as f:
            f.write(json.dumps(record) + "\n")
        chunk += 1
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
