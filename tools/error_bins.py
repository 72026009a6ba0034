#!/usr/bin/env python
"""Where a network's flow goes wrong: per-pixel error statistics binned by the true speed and by
the window's event density, beside zero flow, per dataset and dt.

    python tools/error_bins.py --data ../shared/devval/*.h5 --models ev-mgrflownet-cpu-synthetic \\
        ev-mgrflownet-cpu-dr --dt 1 4 --out runs/diagnosis/devval.json

Each model is run by agents.evaluation.evaluate exactly as scripts/evaluate.py runs it (whole
frames at native size, recurrent state carried, windows of dt ground-truth intervals); the
statistics are gathered by its scorer hook over the AEE's own pixels (events in the window and
valid, finite ground truth). Pixels are pooled over all windows (scripts/evaluate.py averages per
window, then per sequence). Per bin:

- share: % of the scored pixels; AEE and zero flow's AEE (= mean |gt|);
- gain = sum(pred . gt) / sum(gt . gt): the least-squares magnitude ratio (> 1 overshoots, < 1
  undershoots, 0 for zero flow); cos: mean cosine of pred and gt where both are non-zero;
- out %: AEE > 3 px and > 5 % of |gt| (losses.flow_error's outlier rule).

Speed bins: |gt| / dt in px per frame interval. Density bins: the window's events / (H W),
quantiles over all windows of the dataset and dt (their edges printed). Per sequence: events per
pixel per window, events per active pixel, mean |gt| and |pred|, |pred| on pixels slower than
0.5 px/frame, the % of pixels whose true displacement exceeds the output cap (+-flow_scaling per
component), the gain and the largest predicted component (the JSON also holds the % of pixels
within 5 % of the cap, and the AEE as scripts/evaluate.py averages it). --data may be given
several times, one dataset each: a synthetic split name, or recording files / folders.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402
import torch  # noqa: E402

from agents.evaluation import evaluate  # noqa: E402
from agents.policy import RecurrentPolicy  # noqa: E402
from envs.representations import event_mask  # noqa: E402
from losses import flow_error  # noqa: E402

SPEED_EDGES = (0.0, 0.5, 1.0, 2.0, 4.0, 8.0, 16.0, np.inf)
STATS = ("n", "aee", "aee_zero", "pg", "gg", "cos", "n_cos", "out", "out_zero", "pred", "over_cap", "saturated")
S = {k: i for i, k in enumerate(STATS)}
ZERO = "zero flow"


def pixel_stats(pred: np.ndarray, gt: np.ndarray, cap: float) -> np.ndarray:
    """Sums of STATS over the given pixels; pred, gt (2, N)."""
    err, mag, pmag = np.hypot(*(pred - gt)), np.hypot(*gt), np.hypot(*pred)
    both = (pmag > 1e-6) & (mag > 1e-6)
    cos = (pred[:, both] * gt[:, both]).sum(0) / (pmag[both] * mag[both])
    return np.array([len(mag), err.sum(), mag.sum(), (pred * gt).sum(), (gt * gt).sum(), cos.sum(), both.sum(),
                     ((err > 3) & (err > 0.05 * mag)).sum(), (mag > 3).sum(), pmag.sum(),
                     (np.abs(gt).max(0) > cap).sum(), (np.abs(pred).max(0) > 0.95 * cap).sum()], np.float64)


def make_scorer(records: list, dt: int, cap: float):
    """An evaluate() scorer: the default AEE / outlier %, and one record per scored window appended to
    the sequence's list in ``records``: (events / (H W), events / active pixel, (bins + 1, STATS) sums,
    largest predicted component)."""
    def scorer_fn(reader):
        windows: list = []
        records.append(windows)

        def score(flow, info, win, size, dt_ratio):
            events = event_mask(win.events, size)
            err = flow_error(flow, info["flow_gt"], info["flow_gt_valid"], events, dt_ratio=dt_ratio)
            gt = info["flow_gt"]
            mask = events & info["flow_gt_valid"] & np.isfinite(gt).all(0)
            if err["n_pixels"] > 0:
                pred, truth = (flow * dt_ratio)[:, mask].astype(np.float64), gt[:, mask].astype(np.float64)
                which = np.digitize(np.hypot(*truth) / dt, SPEED_EDGES[1:-1])
                sums = np.stack([pixel_stats(pred[:, which == b], truth[:, which == b], cap)
                                 for b in range(len(SPEED_EDGES) - 1)])
                n_events = len(win.events)
                windows.append((n_events / (size[0] * size[1]), n_events / events.sum(),
                                np.vstack([sums, sums.sum(0)]), float(np.abs(pred).max())))
            return err, mask
        return score
    return scorer_fn


def summary(sums: np.ndarray, total: float) -> dict:
    """Bin metrics from STATS sums."""
    n = max(sums[S["n"]], 1.0)
    return {"pixels": int(sums[S["n"]]), "share_pct": 100 * sums[S["n"]] / max(total, 1.0),
            "aee": sums[S["aee"]] / n, "aee_zero": sums[S["aee_zero"]] / n,
            "gain": sums[S["pg"]] / sums[S["gg"]] if sums[S["gg"]] > 0 else None,
            "cos": sums[S["cos"]] / sums[S["n_cos"]] if sums[S["n_cos"]] else None,
            "out_pct": 100 * sums[S["out"]] / n, "out_zero_pct": 100 * sums[S["out_zero"]] / n,
            "mean_pred": sums[S["pred"]] / n, "mean_gt": sums[S["aee_zero"]] / n,
            "over_cap_pct": 100 * sums[S["over_cap"]] / n, "saturated_pct": 100 * sums[S["saturated"]] / n}


def analyse(records: list, names: list[str], density_edges: np.ndarray) -> dict:
    """Speed bins, density bins, per sequence and overall, from one model's window records."""
    flat = [w for seq in records for w in seq]
    total = sum(w[2][-1, S["n"]] for w in flat)
    speed = sum(w[2] for w in flat)
    which = np.clip(np.digitize([w[0] for w in flat], density_edges[1:-1]), 0, len(density_edges) - 2)
    both = [sum((w[2] for w, b in zip(flat, which) if b == k), np.zeros((len(SPEED_EDGES), len(STATS))))
            for k in range(len(density_edges) - 1)]  # density x speed
    density = [d[-1] for d in both]
    sequences = {}
    for name, seq in zip(names, records):
        if seq:
            s = sum(w[2] for w in seq)
            sequences[name] = {**summary(s[-1], s[-1, S["n"]]), "windows": len(seq),
                               "events_per_px": float(np.mean([w[0] for w in seq])),
                               "events_per_active_px": float(np.mean([w[1] for w in seq])),
                               "pred_on_slow": summary(s[0], 1)["mean_pred"], "slow_pixels": int(s[0, S["n"]]),
                               "max_pred_component": max(w[3] for w in seq)}
    return {"overall": summary(speed[-1], total),
            "speed_bins": [{"bin": f"[{a:g},{b:g})", **summary(s, total)}
                           for a, b, s in zip(SPEED_EDGES[:-1], SPEED_EDGES[1:], speed[:-1])],
            "density_bins": [{"bin": f"[{a:.3g},{b:.3g})", "windows": int((which == k).sum()), **summary(s, total)}
                             for k, (a, b, s) in enumerate(zip(density_edges[:-1], density_edges[1:], density))],
            "density_x_speed": [[summary(c, total) for c in d[:-1]] for d in both],
            "sequences": sequences}


def fmt(v, digits=2) -> str:
    return "-" if v is None else f"{v:.{digits}f}"


def bin_table(title: str, results: dict, key: str) -> str:
    """Rows = bins; share, zero flow's AEE / out %, then per model AEE, gain, cos, out %."""
    models = [m for m in results if m != ZERO]
    head = ["bin"] + ["windows"] * (key == "density_bins") + ["px %", "zero AEE", "zero out %"]
    head += [f"{short(m, models)} {c}" for m in models for c in ("AEE", "gain", "cos", "out %")]
    lines = [f"**{title}**", "", "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for i, row in enumerate(results[ZERO][key]):
        cells = [row["bin"]] + ([str(row["windows"])] if key == "density_bins" else [])
        cells += [fmt(row["share_pct"], 1), fmt(row["aee_zero"]), fmt(row["out_zero_pct"], 1)]
        for m in models:
            r = results[m][key][i]
            cells += [fmt(r["aee"]), fmt(r["gain"]), fmt(r["cos"]), fmt(r["out_pct"], 1)] if r["pixels"] else ["-"] * 4
        lines.append("| " + " | ".join(cells) + " |")
    o = {m: results[m]["overall"] for m in results}
    lines.append("| all | " + "| " * (key == "density_bins") + f"100 | {fmt(o[ZERO]['aee'])} | "
                 + f"{fmt(o[ZERO]['out_pct'], 1)} | " + " | ".join(
                     f"{fmt(o[m]['aee'])} | {fmt(o[m]['gain'])} | {fmt(o[m]['cos'])} | {fmt(o[m]['out_pct'], 1)}"
                     for m in models) + " |")
    return "\n".join(lines)


def sequence_table(title: str, results: dict) -> str:
    models = [m for m in results if m != ZERO]
    head = ["sequence", "windows", "ev/px/win", "ev/active px", "mean abs gt", "gt > cap %"]
    head += [f"{short(m, models)} {c}" for m in models
             for c in ("AEE", "gain", "mean abs pred", "abs pred <0.5 px/f", "max comp")]
    lines = [f"**{title}**", "", "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for name, z in results[ZERO]["sequences"].items():
        cells = [name, str(z["windows"]), fmt(z["events_per_px"], 3), fmt(z["events_per_active_px"]),
                 fmt(z["mean_gt"]), fmt(z["over_cap_pct"], 1)]
        for m in models:
            r = results[m]["sequences"][name]
            cells += [fmt(r["aee"]), fmt(r["gain"]), fmt(r["mean_pred"]), fmt(r["pred_on_slow"]) if r["slow_pixels"] else "-",
                      fmt(r["max_pred_component"], 1)]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def cross_table(title: str, results: dict) -> str:
    """Gain per density bin (rows) and speed bin (columns), each model's in one cell: is the
    magnitude's error a matter of density once the speed is fixed?"""
    models = [m for m in results if m != ZERO]
    speeds = [r["bin"] for r in results[ZERO]["speed_bins"]]
    lines = [f"**{title}** (cells: gain " + " / ".join(short(m, models) for m in models) + ")", "",
             "| density bin | " + " | ".join(speeds) + " |", "|" + "---|" * (len(speeds) + 1)]
    for k, row in enumerate(results[ZERO]["density_bins"]):
        cells = [" / ".join(fmt(results[m]["density_x_speed"][k][j]["gain"]) for m in models)
                 if results[ZERO]["density_x_speed"][k][j]["pixels"] >= 100 else "-" for j in range(len(speeds))]
        lines.append(f"| {row['bin']} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def short(name: str, names: list[str]) -> str:
    """A model's name without the prefix the models share (e.g. 'synthetic', 'dr')."""
    prefix = os.path.commonprefix(names).rpartition("-")[0] if len(names) > 1 else ""
    return name[len(prefix) + 1:] if prefix else name


def label_of(items: list[str]) -> str:
    if len(items) == 1 and not Path(items[0]).exists():
        return items[0]  # a synthetic split
    parents = {Path(i).resolve().parent.name if Path(i).is_file() else Path(i).name for i in items}
    return "+".join(sorted(parents))


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", nargs="+", action="append", help="one dataset (repeat for more): split or files")
    p.add_argument("--models", nargs="+", default=["ev-mgrflownet-cpu-synthetic"], help="shipped model names")
    p.add_argument("--dt", type=int, nargs="+", default=[1, 4], help="ground-truth intervals per window")
    p.add_argument("--max-windows", type=int, default=None, help="per sequence (default: all)")
    p.add_argument("--density-bins", type=int, default=5, help="quantile bins of events / (H W) per window")
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--out", default="runs/diagnosis/error_bins.json", help="JSON path (tables also to .md)")
    args = p.parse_args(argv)
    torch.set_num_threads(args.threads)
    os.environ.setdefault("OMP_NUM_THREADS", str(args.threads))
    policies = {ZERO: None, **{m: RecurrentPolicy.from_pretrained(m) for m in args.models}}
    caps = {m: (pol.model.flow_scaling if pol is not None else 32.0) for m, pol in policies.items()}
    report, tables = {}, []
    for items in args.data or [["synthetic-dr-val"]]:
        label = label_of(items)
        for dt in args.dt:
            records, names, seconds, window_means = {}, {}, {}, {}
            for m, policy in policies.items():
                began, records[m] = time.perf_counter(), []
                rows = evaluate(policy, items if len(items) > 1 else items[0], window="frames", window_size=dt,
                                max_windows=args.max_windows, progress=False,
                                scorer_fn=make_scorer(records[m], dt, caps[m if m != ZERO else args.models[0]]))
                names[m], seconds[m] = [r.name for r in rows], time.perf_counter() - began
                window_means[m] = {r.name: r.mean("aee") for r in rows}
                print(f"[{label} dt={dt}] {m}: {sum(r.windows for r in rows)} windows, {seconds[m]:.0f} s, "
                      f"mean sequence AEE {np.nanmean([r.mean('aee') for r in rows]):.3f}", flush=True)
            density = [w[0] for seq in records[ZERO] for w in seq]
            edges = np.quantile(density, np.linspace(0, 1, args.density_bins + 1))
            edges[0], edges[-1] = 0.0, np.inf
            results = {m: {**analyse(records[m], names[m], edges), "seconds": seconds[m], "flow_scaling": caps[m]}
                       for m in policies}
            for m, by_name in window_means.items():  # scripts/evaluate.py's AEE: mean over windows
                for name, aee in by_name.items():
                    results[m]["sequences"].get(name, {})["aee_window_mean"] = aee
            report.setdefault(label, {})[f"dt{dt}"] = results
            what = f"{label}, dt = {dt}"
            tables += [bin_table(f"{what}: speed bins (px per frame interval)", results, "speed_bins"),
                       bin_table(f"{what}: density bins (events / (H W) per window, quantiles)", results,
                                 "density_bins"),
                       cross_table(f"{what}: gain by density (rows) and speed (columns)", results),
                       sequence_table(f"{what}: per sequence", results)]
            print("\n\n".join(tables[-4:]) + "\n", flush=True)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(report, indent=1, default=float) + "\n")
    out.with_suffix(".md").write_text("\n\n".join(tables) + "\n")
    print(f"wrote {out} and {out.with_suffix('.md')}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
