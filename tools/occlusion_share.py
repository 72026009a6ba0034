#!/usr/bin/env python
"""How much of a method's error sits where the scene changes layer within the window: pixels that a
moving object covers or uncovers between the window's start and end (our simulator's recordings
only, where the scene's layers are known).

    python tools/occlusion_share.py --data synthetic-transfer-train:16 --dt 2 --max-windows 6 \\
        --models cmax ev-mgrflownet-cpu-long-windows --out runs/diagnosis/occlusion.json

Why it matters: the ground truth (as in MVSEC, DSEC and devval) is the displacement of the scene
point seen at each pixel at the window's START. Where an object moves over a still background,
the pixels it covers during the window show background at the start (true flow: the
background's), yet every event there is fired by the object's leading edge, so a flow that
aligns the events (contrast maximisation, and any network trained on L_HMC or on its solves)
puts the object's motion there. With a still camera and fast objects that region is a large
share of the scored pixels.

Each method runs through agents.evaluation.evaluate as scripts/evaluate.py runs it (whole frames,
recurrent state carried); the scorer splits the AEE's own pixels (events in the window, valid
ground truth) into "changed" (the visible layer at any of ``--probes`` times in the window
differs from the one at its start) and "kept". Methods: shipped model names, ``cmax`` (the
evaluation's --cmax solve) and zero flow (always).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402
import torch  # noqa: E402

from agents.cmax import ContrastMaximisationPolicy  # noqa: E402
from agents.evaluation import evaluate  # noqa: E402
from agents.policy import RecurrentPolicy  # noqa: E402
from envs.atomic import temporary_path  # noqa: E402
from envs.representations import event_mask  # noqa: E402
from envs.simulator.scene import Scene  # noqa: E402
from losses import flow_error  # noqa: E402

ZERO = "zero flow"


def layer_changes(scene: Scene, t_start: int, t_end: int, probes: int) -> np.ndarray:
    """(H, W) bool: pixels whose visible layer at one of ``probes`` times in (t_start, t_end)
    (µs, the last just before t_end) differs from the one at t_start."""
    first = scene.visible_layers(t_start * 1e-6)
    changed = np.zeros(first.shape, bool)
    for t in np.linspace(t_start, t_end - 1, probes + 1)[1:]:
        changed |= scene.visible_layers(float(t) * 1e-6) != first
    return changed


def make_scorer(rows: list, probes: int):
    """An evaluate() scorer: the default AEE, and per window the error sums over kept and changed
    pixels appended to ``rows`` as (sequence, n_kept, err_kept, gt_kept, n_changed, err_changed, gt_changed)."""
    def scorer_fn(reader):
        config = getattr(reader, "config", None)
        if config is None:
            raise SystemExit(f"{getattr(reader, 'path', reader)}: not a recording of this project's simulator "
                             "(its scene layers are unknown); use a synthetic split")
        scene, name = Scene(config), Path(str(getattr(reader, "path", "?"))).stem

        def score(flow, info, win, size, dt_ratio):
            events = event_mask(win.events, size)
            err = flow_error(flow, info["flow_gt"], info["flow_gt_valid"], events, dt_ratio=dt_ratio)
            gt = info["flow_gt"]
            mask = events & info["flow_gt_valid"] & np.isfinite(gt).all(0)
            changed = layer_changes(scene, int(win.t_start), int(win.t_end), probes)
            e = np.hypot(*(flow * dt_ratio - gt))
            g = np.hypot(*gt)
            rows.append((name, *(v for part in (mask & ~changed, mask & changed)
                                 for v in (int(part.sum()), float(e[part].sum()), float(g[part].sum())))))
            return err, mask
        return score
    return scorer_fn


def summarise(rows: list) -> dict:
    """Pixels and AEE over ``rows`` (a scorer's: name, then count, error sum and zero flow's error
    sum on the kept and on the changed pixels), split kept / changed; None where a part has no pixel."""
    totals = np.array([r[1:] for r in rows], np.float64).sum(0) if rows else np.zeros(6)
    kept_px, kept_err, kept_zero, changed_px, changed_err, changed_zero = totals
    pixels = kept_px + changed_px

    def mean(total: float, count: float) -> float | None:
        return total / count if count else None

    return {"pixels": int(pixels), "changed_pct": mean(100 * changed_px, pixels),
            "aee": mean(kept_err + changed_err, pixels),
            "aee_kept": mean(kept_err, kept_px), "aee_changed": mean(changed_err, changed_px),
            "zero_kept": mean(kept_zero, kept_px), "zero_changed": mean(changed_zero, changed_px),
            "error_on_changed_pct": mean(100 * changed_err, kept_err + changed_err)}


def fmt(v, digits=3) -> str:
    return "-" if v is None else f"{v:.{digits}f}"


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", default="synthetic-transfer-train:16", help="a synthetic split (SPLIT or SPLIT:N)")
    p.add_argument("--models", nargs="*", default=["cmax"], help="shipped model names and/or 'cmax'")
    p.add_argument("--dt", type=int, nargs="+", default=[2], help="ground-truth intervals per window")
    p.add_argument("--max-windows", type=int, default=None, help="per sequence (default: all)")
    p.add_argument("--probes", type=int, default=4, help="times in the window at which the layers are compared")
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--out", default="runs/diagnosis/occlusion.json", help="JSON path (the table also to .md)")
    args = p.parse_args(argv)
    torch.set_num_threads(args.threads)
    os.environ.setdefault("OMP_NUM_THREADS", str(args.threads))
    methods = {ZERO: None}
    for m in args.models:
        methods[m] = ContrastMaximisationPolicy() if m == "cmax" else RecurrentPolicy.from_pretrained(m)
    report, lines = {}, []
    for dt in args.dt:
        per = {}
        for name, policy in methods.items():
            rows: list = []
            evaluate(policy, args.data, window="frames", window_size=dt, max_windows=args.max_windows,
                     progress=False, scorer_fn=make_scorer(rows, args.probes))
            per[name] = {"all": summarise(rows),
                         "sequences": {s: summarise([r for r in rows if r[0] == s]) for s in dict.fromkeys(r[0] for r in rows)}}
            o = per[name]["all"]
            print(f"[{args.data} dt={dt}] {name}: AEE {fmt(o['aee'])} (kept pixels {fmt(o['aee_kept'])}, changed "
                  f"{fmt(o['aee_changed'])}; {fmt(o['changed_pct'], 1)} % of pixels changed, "
                  f"{fmt(o['error_on_changed_pct'], 1)} % of the error there)", flush=True)
        report[f"dt{dt}"] = per
        names = [m for m in methods if m != ZERO]
        head = ["sequence", "changed px %", "zero kept", "zero changed"] + [
            f"{m} {c}" for m in names for c in ("AEE", "kept", "changed", "% of error on changed")]
        lines += [f"**{args.data}, dt = {dt}** (AEE over the scored pixels, split by whether the visible layer changes in the window)",
                  "", "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
        for seq in list(per[ZERO]["sequences"]) + ["all"]:
            z = per[ZERO]["all"] if seq == "all" else per[ZERO]["sequences"][seq]
            cells = [seq, fmt(z["changed_pct"], 1), fmt(z["zero_kept"]), fmt(z["zero_changed"])]
            for m in names:
                r = per[m]["all"] if seq == "all" else per[m]["sequences"][seq]
                cells += [fmt(r["aee"]), fmt(r["aee_kept"]), fmt(r["aee_changed"]), fmt(r["error_on_changed_pct"], 1)]
            lines.append("| " + " | ".join(cells) + " |")
        lines.append("")
        print("\n".join(lines[-(len(per[ZERO]["sequences"]) + 6):]), flush=True)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    for path, text in ((out, json.dumps({"data": args.data, "max_windows": args.max_windows, **report}, indent=1)),
                       (out.with_suffix(".md"), "\n".join(lines))):
        tmp = temporary_path(path)  # whole files or none
        tmp.write_text(text + "\n")
        os.replace(tmp, path)
    print(f"wrote {out} and {out.with_suffix('.md')}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
