#!/usr/bin/env python
"""The paper's ablations on the synthetic benchmark, at one budget, written into docs/results.md.

Trains each configuration for --minutes with the same recipe (the options after `--`, default:
per-window training on the loss itself, as in the paper, with this project's CPU settings), evaluates it on the synthetic test split at dt = 1 and dt = 4, and
writes two tables in the layout of the paper's Tables 2 (network ablations) and 3 (losses and
baselines) between the markers ``<!-- ablations:start -->`` / ``<!-- ablations:end -->`` of
--report. The main configuration (EV-MGRFlowNet + L_HMC) runs with every --seeds entry and its
seed-to-seed spread is reported; the others run with the first seed.

  python scripts/ablations.py --minutes 6 --seeds 0 1 2                 # about 60 CPU-minutes
  python scripts/ablations.py --minutes 1 --only mgr-hmc --report ''    # a quick look, no report

Resumable: a configuration whose evaluation exists is not run again; one whose training was cut
off continues from its checkpoint for the rest of its budget. Rerun the same command to finish.
"""

from __future__ import annotations

import argparse
import datetime
import json
import statistics
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

import evaluate as evaluate_script  # noqa: E402
import train as train_script  # noqa: E402

# name: (label, train options)
CONFIGS = {
    "mgr-hmc": ("EV-MGRFlowNet, L_HMC", ["--model", "ev-mgrflownet", "--loss", "hmc"]),
    "mgr-no-st": ("EV-MGRFlowNet without ST-ConvGRU, L_HMC",
                  ["--model", "ev-mgrflownet", "--loss", "hmc", "--model-kwarg", "use_st_convgru=false"]),
    "mgr-no-prior": ("EV-MGRFlowNet without prior flows, L_HMC",
                     ["--model", "ev-mgrflownet", "--loss", "hmc", "--model-kwarg", "use_prior_flow=false"]),
    "mgr-at": ("EV-MGRFlowNet, L_AT", ["--model", "ev-mgrflownet", "--loss", "at"]),
    "convgru-at": ("ConvGRU-EV-FlowNet, L_AT", ["--model", "convgru-ev-flownet", "--loss", "at"]),
    "convgru-hmc": ("ConvGRU-EV-FlowNet, L_HMC", ["--model", "convgru-ev-flownet", "--loss", "hmc"]),
    "evflownet-hmc": ("EV-FlowNet, L_HMC", ["--model", "ev-flownet", "--loss", "hmc"]),
}
TABLE2 = ["mgr-hmc", "mgr-no-st", "mgr-no-prior"]
TABLE3 = ["mgr-hmc", "mgr-at", "convgru-hmc", "convgru-at", "evflownet-hmc"]
# paper, MVSEC dt = 1 AEE averaged over its four sequences (REFERENCE section 7)
PAPER_DT1 = {
    "mgr-hmc": (0.28 + 0.41 + 0.70 + 0.59) / 4,
    "mgr-no-st": (0.32 + 0.45 + 0.80 + 0.67) / 4,
    "mgr-no-prior": (0.30 + 0.41 + 0.78 + 0.63) / 4,
    "mgr-at": (0.37 + 0.52 + 0.96 + 0.79) / 4,
    "convgru-at": (0.47 + 0.60 + 1.17 + 0.93) / 4,
}
# the paper's way of training (the per-window loss itself), with this project's CPU settings
DEFAULT_RECIPE = ["--width", "cpu", "--input", "voxel_grid", "--lr", "1e-3", "--flow-scaling", "32", "--head-init", "0.01",
                  "--crop", "64", "64", "--random-crop", "--window-size", "2", "3", "4"]
START, END = "<!-- ablations:start -->", "<!-- ablations:end -->"


def trained_minutes(run: Path) -> float:
    """Training time already spent in run/train (elapsed_s restarts at each resume)."""
    path = run / "train" / "metrics.jsonl"
    if not path.exists():
        return 0.0
    total, last = 0.0, 0.0
    for line in path.read_text().splitlines():
        e = json.loads(line).get("elapsed_s")
        if e is None:
            continue
        if e < last:
            total += last
        last = e
    return (total + last) / 60


def run_config(out: Path, name: str, seed: int, minutes: float, recipe: list[str], eval_args: list[str]) -> dict:
    run = out / f"{name}-s{seed}"
    results = run / "eval" / "results.json"
    if not results.exists():
        done = trained_minutes(run)
        checkpoint = run / "train" / "checkpoint.pt"
        if checkpoint.exists() and done >= minutes:
            pass
        elif checkpoint.exists():
            print(f"[ablations] {name} seed {seed}: resuming for {minutes - done:.1f} more min", flush=True)
            train_script.main(["--resume", "--minutes", f"{minutes - done:.3f}", "--out", str(run / "train"), "--no-progress"])
        else:
            print(f"[ablations] {name} seed {seed}: training {minutes:g} min", flush=True)
            train_script.main([*recipe, *CONFIGS[name][1], "--seed", str(seed), "--minutes", str(minutes),
                               "--steps", "1000000", "--out", str(run / "train"), "--val-data", "", "--no-progress"])
        evaluate_script.main(["--checkpoint", str(checkpoint), "--name", name, "--out", str(run / "eval"),
                              "--pictures", "0", "--no-progress", *eval_args])
    payload = json.loads(results.read_text())
    rows = [json.loads(line) for line in (run / "train" / "metrics.jsonl").read_text().splitlines()]
    payload["steps"] = max((r["step"] for r in rows if "loss" in r), default=0)
    return payload


def zero_flow(out: Path, eval_args: list[str]) -> dict:
    results = out / "zero" / "results.json"
    if not results.exists():
        evaluate_script.main(["--out", str(out / "zero"), "--pictures", "0", "--no-progress", *eval_args])
    return json.loads(results.read_text())


def _cell(values: list[float], digits: int = 3) -> str:
    if len(values) == 1:
        return f"{values[0]:.{digits}f}"
    return f"{statistics.mean(values):.{digits}f} ± {statistics.stdev(values):.{digits}f}"


def render(results: dict[str, list[dict]], zero: dict, args, recipe: list[str]) -> str:
    def metric(name, key, sub):
        return [r["overall"][key][sub] for r in results[name]]

    def row(name):
        label = CONFIGS[name][0]
        n = len(results[name])
        seeds = f" ({n} seeds)" if n > 1 else ""
        cells = [_cell(metric(name, "dt1", "aee")), _cell(metric(name, "dt1", "outlier_pct"), 1),
                 _cell(metric(name, "dt4", "aee")), _cell(metric(name, "dt4", "outlier_pct"), 1),
                 _cell(metric(name, "dt1", "cosine"), 2), _cell(metric(name, "dt1", "hmc")),
                 str(round(statistics.mean(r["steps"] for r in results[name]))),
                 f"{PAPER_DT1[name]:.3f}" if name in PAPER_DT1 else "n/a"]
        return f"| {label}{seeds} | " + " | ".join(cells) + " |"

    z1, z4 = zero["overall"]["dt1"], zero["overall"]["dt4"]
    zero_row = (f"| zero flow (reference) | {z1['aee']:.3f} | {z1['outlier_pct']:.1f} | {z4['aee']:.3f} | "
                f"{z4['outlier_pct']:.1f} | n/a | {z1['hmc']:.3f} | 0 | n/a |")
    head = ("| configuration | AEE dt=1 | outliers % dt=1 | AEE dt=4 | outliers % dt=4 | cos dt=1 | L_HMC dt=1 | "
            "Adam steps | paper MVSEC dt=1 AEE (4-seq mean) |\n|---|---:|---:|---:|---:|---:|---:|---:|---:|")
    lines = [
        START,
        f"Generated by `python scripts/ablations.py --minutes {args.minutes:g} --seeds {' '.join(map(str, args.seeds))}"
        f" -- {' '.join(recipe)}` on {datetime.date.today().isoformat()}.",
        f"Budget: {args.minutes:g} minutes of training per configuration on the project's 2-core CPU "
        f"(one process per run{', ' + args.threads_note if args.threads_note else ''}); "
        f"seeds {', '.join(map(str, args.seeds))} for the main configuration, seed {args.seeds[0]} for the others. "
        f"Evaluated on `{args.eval_data}` ("
        + (f"the first {args.max_windows} windows of each sequence" if args.max_windows else "every window")
        + "; 256x256 sequences centre-cropped to 128x128), "
        "dt = 1 and dt = 4. The paper column is MVSEC, a different data set: compare orderings, not values. "
        "Mean ± sample standard deviation over seeds where there are several.",
        "",
        "**Table 2 layout: network ablations (L_HMC)**",
        "",
        head, zero_row, *[row(n) for n in TABLE2 if n in results],
        "",
        "**Table 3 layout: losses and baselines**",
        "",
        head, zero_row, *[row(n) for n in TABLE3 if n in results],
        END,
    ]
    return "\n".join(lines)


def write_report(path: Path, block: str) -> None:
    text = path.read_text() if path.exists() else ""
    if START in text and END in text:
        text = text[: text.index(START)] + block + text[text.index(END) + len(END):]
    else:
        text = text.rstrip() + "\n\n## Ablations (paper Tables 2 and 3 layout)\n\n" + block + "\n"
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(text)
    tmp.replace(path)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--minutes", type=float, default=6.0, help="training budget per run (default 6)")
    p.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2], help="seeds of the main configuration")
    p.add_argument("--only", nargs="*", default=None, choices=list(CONFIGS), help="run only these configurations")
    p.add_argument("--out", default="runs/ablations")
    p.add_argument("--report", default="docs/results.md", help="file to write the tables into ('' for none)")
    p.add_argument("--eval-data", default="synthetic-test")
    p.add_argument("--max-windows", type=int, default=None, help="per test sequence (default: all)")
    p.add_argument("--threads-note", default="", help="added to the budget line, e.g. '1 thread each, two at a time'")
    p.add_argument("recipe", nargs="*", help="train.py options after `--` (default: the shipped recipe)")
    argv = list(sys.argv[1:] if argv is None else argv)
    cut = argv.index("--") if "--" in argv else len(argv)
    args = p.parse_args(argv[:cut])
    recipe = [*args.recipe, *argv[cut + 1:]] or DEFAULT_RECIPE
    out = Path(args.out)
    eval_args = ["--data", args.eval_data, "--dt", "1", "4"]
    if args.max_windows:
        eval_args += ["--max-windows", str(args.max_windows)]
    names = args.only or list(CONFIGS)
    results: dict[str, list[dict]] = {}
    for name in names:
        seeds = args.seeds if name == "mgr-hmc" else args.seeds[:1]
        results[name] = [run_config(out, name, seed, args.minutes, recipe, eval_args) for seed in seeds]
    zero = zero_flow(out, eval_args)
    block = render(results, zero, args, recipe)
    print(block)
    if args.report:
        write_report(Path(args.report), block)
        print(f"[ablations] wrote the tables into {args.report}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
