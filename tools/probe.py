#!/usr/bin/env python
"""One recipe probe: train for a time budget, evaluate on held-out synthetic sequences, print
one summary line (and append it to OUT/probes.jsonl). Used in the first rounds of docs/history/.

  python tools/probe.py NAME --minutes 8 -- --flow-scaling 16 --lr 1e-3
  python tools/probe.py sup  --minutes 8 -- --loss supervised

Summary: training loss vs zero flow's over the last 20 steps (same windows), and on the
evaluation data (dt = 1, first --eval-windows windows of each sequence): AEE, outlier %,
cosine to the true flow, L_HMC, for the model and for zero flow.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402

from evflow_cli.commands import evaluate as evaluate_script  # noqa: E402
from evflow_cli.commands import train as train_script  # noqa: E402


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("name")
    p.add_argument("--minutes", type=float, default=8.0)
    p.add_argument("--out", default="runs/probes")
    p.add_argument("--eval-data", default="synthetic-test")
    p.add_argument("--eval-windows", type=int, default=15)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("train_args", nargs="*", help="train.py options, after a '--'")
    argv = list(sys.argv[1:] if argv is None else argv)
    cut = argv.index("--") if "--" in argv else len(argv)
    args = p.parse_args(argv[:cut])
    args.train_args = [*args.train_args, *argv[cut + 1 :]]
    run = Path(args.out) / args.name
    train_script.main(["--minutes", str(args.minutes), "--steps", "100000", "--out", str(run / "train"), "--val-data", "",
                       "--no-progress", "--seed", str(args.seed), *args.train_args])
    evaluate_script.main(["--checkpoint", str(run / "train" / "checkpoint.pt"), "--name", args.name, "--zero",
                          "--data", args.eval_data, "--dt", "1", "--max-windows", str(args.eval_windows),
                          "--out", str(run / "eval"), "--pictures", "1", "--no-progress"])
    rows = [json.loads(line) for line in (run / "train" / "metrics.jsonl").read_text().splitlines()]
    steps = [r for r in rows if "loss" in r][-20:]
    ev = json.loads((run / "eval" / "results.json").read_text())
    model, zero = ev["overall"]["dt1"], ev["baselines"]["zero flow"]["overall"]["dt1"]
    summary = {
        "name": args.name, "args": " ".join(args.train_args), "minutes": args.minutes, "seed": args.seed,
        "steps": rows[-1]["step"] if rows else 0,
        "train_loss": float(np.mean([r["loss"] for r in steps])), "train_zero": float(np.mean([r["zero_flow_loss"] for r in steps])),
        "aee": model["aee"], "aee_zero": zero["aee"], "outlier_pct": model["outlier_pct"], "cosine": model["cosine"],
        "hmc": model["hmc"], "hmc_zero": model["hmc_zero"],
    }
    with open(Path(args.out) / "probes.jsonl", "a") as f:
        f.write(json.dumps(summary) + "\n")
    print("PROBE " + json.dumps(summary))
    return 0


if __name__ == "__main__":
    sys.exit(main())
