"""Evaluate flow policies on recordings: AEE / outlier % (where there is ground truth),
L_HMC against zero flow's, FWL and RSAT, per sequence; Markdown table + JSON + PNG pictures.

Examples:
  python scripts/evaluate.py --pretrained --zero                                   # the default model in its mode
  python scripts/evaluate.py --checkpoint runs/mgr/checkpoint.pt --zero            # synthetic-test
  python scripts/evaluate.py --checkpoint ckpt.pt --data rec1.h5 rec2.h5 --window-size 4
  python scripts/evaluate.py --model mypkg.models:build --data synthetic-test     # untrained plug-in
  python scripts/evaluate.py --checkpoint ckpt.pt --mvsec /data/mvsec --window-size 1   # MVSEC protocol
  python scripts/evaluate.py --checkpoint ckpt.pt --mvsec /data/mvsec --mvsec-grid gt --window-size 1   # 20 Hz
  python scripts/evaluate.py --checkpoint ckpt.pt --protocol dsec --data seq/events/left/events.h5 \\
      --dsec-flow train_optical_flow/seq/flow/forward                             # DSEC dense scores
  python scripts/evaluate.py --checkpoint ckpt.pt --protocol dsec --data test_events/interlaken_00_b \\
      --dsec-test-timestamps test_forward_optical_flow_timestamps --dsec-submission runs/dsec_submission
  python scripts/evaluate.py --pretrained --zero --cmax --data synthetic-stress    # with the model-free row
  python scripts/evaluate.py --pretrained --refine 30 --data rec.h5                # + test-time refinement
  python scripts/evaluate.py --pretrained --split dt --zero --cmax --data synthetic-stress   # network at a 1-frame cadence

Each recording is evaluated whole at its own sensor size (the networks pad to a multiple of 16
and crop their flow back) unless --crop is given. Each sequence is rolled from its first window
with the recurrent state carried across windows and reset between sequences. Windows (--window
frames, the default) follow the ground-truth grid where a recording has one, else its APS frame
times, else fixed 30 Hz intervals, --window-size of them per window (default 1 and 4 when a
recording has ground truth, else 1; --dt, the paper's name, is the same option), a table for
each; each table's title names the windowing. With --window time/count, give --dt-ratio
(ground-truth interval / input window) if they differ.

--mvsec scores MVSEC as published (docs/protocols.md): the valid ranges index the 20 Hz
ground-truth times, windows of --window-size (dt) image frames (or 20 Hz steps with --mvsec-grid
gt) inside them, Zhu's ground truth (--mvsec-gt chain to chain the maps), the car's hood out of
outdoor_day1, dt = 4 at stride 4 and at stride 1 (overlapping) unless --stride says which; each
AEE shows its window count. --protocol dsec scores DSEC densely (EPE, 1PE, 2PE, 3PE, angular
error on every valid ground-truth pixel) and, with --dsec-submission, writes the benchmark's PNGs.

--cmax adds per-window contrast maximisation of the same loss (no network, no ground truth;
agents/cmax.py): the reference a learned model must beat. --refine K adds, for each model, a
row with its flow refined by K steps of that solver on the window's own events.

OUT/table.md and the JSON are claimed before any work (envs.outputs.Output): never an input,
never a file of an earlier evaluation (nor its pictures/ or DSEC submission) without
--overwrite, never one another process is writing. Numbers are checked when parsed; a user error
prints one line (``error: ...``) and exits 2 (evflow_cli.commands.cli; EVFLOW_DEBUG=1: traceback).
"""

from __future__ import annotations

import argparse
import contextlib
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import agents.pretrained as pretrained_module
from agents.checkpoint import load_model
from agents.evaluation import TABLE_LEGEND, evaluate, results_json, results_table, windowing_of
from agents.options import (
    DeviceOptions,
    ModelWidth,
    Progress,
    RecordingOptions,
    Windows,
    check_choices,
    command_parser,
    default_device,
    fraction,
    non_negative_float,
    non_negative_int,
    option,
    parse_options,
    positive_float,
    positive_int,
)
from agents.policy import RecurrentPolicy
from agents.registry import make_model, width_kwargs
from agents.wrappers.mirror import MIRROR_SETS, MirrorPolicy
from agents.wrappers.subwindows import SubWindowPolicy
from envs.outputs import Output


@dataclass
class EvaluateOptions(ModelWidth, Windows, RecordingOptions, DeviceOptions, Progress):
    """What scripts/evaluate.py evaluates, on what, and where it writes (one option per field;
    the string under a field is its help; the windows, recordings and device are the groups every
    command shares, agents.options)."""

    config: str | None = option(None, metavar="FILE")
    """options from a TOML or JSON file of option = value (those given beside it win)"""
    checkpoint: list[str] = option(nargs="*", default_factory=list)
    """checkpoint(s) written by scripts/train.py"""
    pretrained: list[str] | None = option(None, nargs="*", metavar="NAME")
    """shipped pretrained model(s) by name (see agents/weights/; no name: the default one)"""
    name: list[str] | None = option(None, nargs="*")
    """row names for the checkpoints (default: file stem / parent dir)"""
    model: str | None = None
    """evaluate an untrained model (registry name or package.module:factory)"""
    zero: bool = False
    """add the zero-flow baseline row"""
    cmax: bool = False
    """add per-window contrast maximisation (no network, no ground truth; agents/cmax.py)"""
    cmax_prior: float | None = option(None, metavar="C", type=non_negative_float)
    """also add the --cmax solve held toward zero flow with weight C / the window's events (30000 as measured: still, sparse windows stay still)"""
    refine: int | None = option(None, metavar="K", type=non_negative_int)
    """also evaluate each model with its flow refined by K contrast-maximisation steps"""
    refine_solver: Literal["fine", "cmax", "mid"] = "fine"
    """--refine's solve: 'fine' (one 16-cell level, a local correction), 'cmax' (the --cmax coarse-to-fine solve started from the network's flow, K steps over its levels) or 'mid' (its two finer levels)"""
    refine_prior: float = option(0.0, type=non_negative_float)
    """--refine holds the flow to the network's with this weight (mean square of the correction in flow-scaling units; 0: none)"""
    refine_accept: float | None = option(None, metavar="A", type=fraction)
    """--refine keeps the refined flow of a window only where it lowers the env's loss (L_HMC with the border rule) by at least the fraction A of the network's (else the network's flow); default: always"""
    finish: bool = False
    """also evaluate each model in the shipped default's mode: its flow finished by the short solve of agents/weights/default.json's "finish" (agents/wrappers/refine.py FinishedPolicy; docs/finish.md)"""
    still: bool = False
    """also evaluate every network row guarded by zero flow: a window's flow is kept only where it lowers the env's loss below zero flow's (agents/wrappers/still.py)"""
    split: str | None = option(None, metavar="N|dt")
    """also evaluate each model stepped through N equal sub-windows of every window, their flows composed (agents/wrappers/subwindows.py); 'dt': one per ground-truth interval (N = the table's dt)"""
    mirror: int | None = option(None, nargs="?", const=4, metavar="N")
    """also evaluate each model (and split row) averaged over its flows on mirrored copies of the input (agents/wrappers/mirror.py): N = 4 (alone: --mirror), the input mirrored left-right, up-down and both, 4 network steps per window; N = 2, the input and its rotation by 180 degrees, 2 steps"""
    data: list[str] = option(default_factory=lambda: ["synthetic-test"])
    """synthetic split, recording files or directories"""
    mvsec: str | None = option(None, metavar="DIR")
    """run the MVSEC protocol on the four sequences in DIR"""
    stride: list[int] | None = option(None, type=positive_int)
    """MVSEC: grid steps between window starts (default: dt, and also 1 for dt = 4)"""
    mvsec_grid: Literal["images", "gt"] = "images"
    """MVSEC windows on the image frames (EV-FlowNet dt) or the 20 Hz ground-truth steps"""
    mvsec_gt: Literal["zhu", "chain"] = "zhu"
    """MVSEC ground truth: Zhu's (containing 20 Hz map scaled) or the maps chained"""
    outdoor_cut: Literal["time", "frames"] = "time"
    """outdoor_day1 span: 222.4-240.4 s or ground-truth indices 4356-4706"""
    no_hood: bool = False
    """MVSEC: score the car's hood rows too"""
    hot_pixels: float | None = option(None, metavar="SIGMA", type=positive_float)
    """MVSEC: leave pixels SIGMA std above the mean event count out of the event mask"""
    protocol: Literal["default", "dsec"] = "default"
    """dsec: dense DSEC scores (EPE, 1PE, 2PE, 3PE, AE) on valid ground truth, no event mask"""
    dsec_flow: str | None = option(None, metavar="DIR")
    """DSEC: the flow PNG folder of the --data recording"""
    dsec_test_timestamps: str | None = option(None, metavar="PATH")
    """DSEC: folder of <sequence>.csv test timestamps (or one CSV): the windows to predict"""
    dsec_submission: str | None = option(None, metavar="DIR")
    """DSEC: write <sequence>/<file_index:06d>.png flows in the benchmark's layout here"""
    dt_ratio: float = option(1.0, type=positive_float)
    """scale predictions by (ground-truth interval / input window)"""
    crop: list[int] | None = option(None, type=non_negative_int)
    """H W (centred) or TOP LEFT H W"""
    max_windows: int | None = option(None, type=positive_int)
    """windows per sequence"""
    out: str = "runs/eval"
    """directory for table.md, results.json and pictures/"""
    json: str | None = None
    """also write the JSON results here (default OUT/results.json)"""
    overwrite: bool = False
    """replace table.md, the JSON, pictures/ (and a DSEC submission) of an earlier evaluation"""
    pictures: int = option(2, type=non_negative_int)
    """windows per sequence drawn as a labelled PNG panel (0: none)"""
    animate: int = option(0, metavar="N", type=non_negative_int)
    """per sequence, a GIF of count image + predicted flow over its first N windows (0: none)"""

    def __post_init__(self) -> None:
        check_choices(self)


def build_parser() -> argparse.ArgumentParser:
    return command_parser(EvaluateOptions, __doc__, defaults={"device": default_device()})


def mvsec_runs(folder: Path, protocol) -> list:
    """The MVSEC protocol (docs/method.md, "Metrics", agents.benchmarks.MVSECProtocol): indoor_flying1-3
    and outdoor_day1, central 256x256 crop, the protocol's windows and scoring."""
    from envs.readers.mvsec import MVSEC_SEQUENCES

    runs = []
    for sequence in MVSEC_SEQUENCES:
        path = folder / f"{sequence}_data.hdf5"
        if not path.exists():
            print(f"[mvsec] {path} not found; skipping {sequence}", file=sys.stderr)
            continue
        runs.append((str(path), "mvsec", protocol.data_options, protocol.windows, protocol.scorer))
    if not runs:
        raise SystemExit(f"--mvsec {folder}: none of {', '.join(s + '_data.hdf5' for s in MVSEC_SEQUENCES)} found")
    return runs


def dsec_sinks(args, protocol, policies: dict) -> dict:
    """Policy name -> DSEC submission writer: DIR itself for one policy, DIR/<name> for several."""
    from agents.benchmarks import DSECSubmissionWriter

    root = Path(args.dsec_submission)
    if len(policies) == 1:
        return {name: DSECSubmissionWriter(root, protocol) for name in policies}
    return {name: DSECSubmissionWriter(root / name.replace(" ", "_"), protocol) for name in policies}


def _add_pretrained(policies: dict, args) -> None:
    """Add the rows of the shipped models ``--pretrained`` names (none given: the default): each
    in the default's mode where that applies (split dt, the finish, with the network alone beside
    it), else as it is."""
    from agents.wrappers.refine import FinishedPolicy

    pretrained = [] if args.pretrained is None else (args.pretrained or [pretrained_module.DEFAULT_PRETRAINED])
    for name in pretrained:
        policy = RecurrentPolicy.from_pretrained(name, device=args.device)
        finish = pretrained_module.default_finish() if default_mode(args) else []
        if default_mode_split(args):  # the default in the mode devval picked (per table: splits = dt)
            policy, label = SubWindowPolicy(policy, splits=1), f"{name} (pretrained) + split dt"
        else:
            label = f"{name} (pretrained)"
        if finish:  # the proposal finished by a short solve; the network alone beside it
            finished = FinishedPolicy(policy, finish)
            policies[f"{label} + finish {' / '.join(f.label() for f in finished.finishes)} (the default's mode)"] = finished
            alone = RecurrentPolicy.from_pretrained(name, device=args.device)  # its own recurrent state
            policies[f"{label}, network alone"] = SubWindowPolicy(alone, splits=1) if default_mode_split(args) else alone
        else:
            policies[label + (" (the default's mode)" if default_mode_split(args) else "")] = policy


def build_policies(args) -> dict:
    """Row name -> policy (None: zero flow), in table order."""
    from agents.cmax import CMaxSettings, ContrastMaximisationPolicy
    from agents.wrappers.refine import FinishedPolicy, RefinedPolicy
    from agents.wrappers.still import StillGuard

    policies: dict = {}
    names = args.name or []
    for i, path in enumerate(args.checkpoint):
        model, payload = load_model(path, map_location=args.device, expect_model=args.model)
        name = names[i] if i < len(names) else Path(path).parent.name or Path(path).stem
        cfg = payload.get("config") or {}
        policies[name] = RecurrentPolicy(model, device=args.device, input_key=cfg.get("input", "count_image"),
                                         voxel_bins=cfg.get("voxel_bins", 5))
    _add_pretrained(policies, args)
    if args.model and not args.checkpoint:
        policies[args.model] = RecurrentPolicy(make_model(args.model, **width_kwargs(args.width)).eval(),
                                               device=args.device)
    if args.split:
        for name, policy in list(policies.items()):
            label = f"{name} + split {args.split}"
            policies[label] = SubWindowPolicy(policy, splits=1 if args.split == "dt" else int(args.split))
    if args.mirror:
        mirrors = MIRROR_SETS[args.mirror]
        suffix = " + mirror" if args.mirror == 4 else f" + mirror {args.mirror}"
        for name, policy in list(policies.items()):
            if isinstance(policy, SubWindowPolicy):
                policies[name + suffix] = SubWindowPolicy(MirrorPolicy(policy.policy, mirrors), splits=policy.splits)
            else:
                policies[name + suffix] = MirrorPolicy(policy, mirrors)
    if args.finish:
        for name, policy in list(policies.items()):
            finished = FinishedPolicy(policy, pretrained_module.default_finish())
            policies[f"{name} + finish {' / '.join(f.label() for f in finished.finishes)}"] = finished
    if args.refine:
        for name, policy in list(policies.items()):
            label = f"{name} + refine {args.refine}" + (f" ({args.refine_solver})" if args.refine_solver != "fine" else "")
            label += f" prior {args.refine_prior:g}" if args.refine_prior else ""
            label += f" accept {args.refine_accept:g}" if args.refine_accept is not None else ""
            policies[label] = RefinedPolicy(policy, steps=args.refine, solver=args.refine_solver,
                                            prior_weight=args.refine_prior, accept=args.refine_accept)
    if args.still:
        for name, policy in list(policies.items()):
            policies[f"{name} + still"] = StillGuard(policy)
    if args.cmax:
        policies["contrast maximisation (no network)"] = ContrastMaximisationPolicy(device=args.device)
    if args.cmax_prior is not None:
        policies[f"contrast maximisation, evidence prior {args.cmax_prior:g} (no network)"] = ContrastMaximisationPolicy(
            CMaxSettings(evidence_prior=args.cmax_prior), device=args.device)
    if args.zero or not policies:
        policies["zero flow"] = None
    return policies


def default_mode(args) -> bool:
    """True when the default model runs in its own mode (``agents/weights/default.json``'s
    ``split`` and ``finish``): ``--pretrained`` without a name and no mode chosen on the command
    line (--split, --mirror, --refine, --still, --finish)."""
    return (args.pretrained == [] and args.split is None and args.mirror is None and not args.refine
            and not args.still and not args.finish)


def default_mode_split(args) -> bool:
    """True when the default model runs in its own mode and that mode steps once per ground-truth
    interval (``default.json``: ``"split": "dt"``): frame windows, not the DSEC protocol."""
    return (default_mode(args) and (args.window == "frames" or bool(args.mvsec)) and args.protocol != "dsec"
            and pretrained_module.default_split() == "dt")


def protocol_settings(args, data) -> list:
    """(key, window size, protocol or None) per table: MVSEC dt and stride combinations, DSEC, or
    the plain windows of --window."""
    from agents.benchmarks import DSECProtocol, MVSECProtocol

    sizes = args.window_sizes()
    if args.protocol == "dsec":
        return [("dsec", sizes[0] if sizes else 1, DSECProtocol(test_timestamps=args.dsec_test_timestamps))]
    if args.mvsec:
        settings = []
        for dt in sizes or [1, 4]:
            for stride in args.stride or ([4, 1] if dt == 4 else [dt]):
                protocol = MVSECProtocol(dt=dt, stride=stride, grid=args.mvsec_grid, ground_truth=args.mvsec_gt,
                                         outdoor_cut=args.outdoor_cut, hood=not args.no_hood,
                                         hot_pixel_sigma=args.hot_pixels)
                settings.append((f"dt{dt}" if stride == dt else f"dt{dt}_stride{stride}", dt, protocol))
        return settings
    if args.window == "frames":
        truth = has_ground_truth(data, args.format, args.data_options())
        return [(f"dt{dt}", dt, None) for dt in sizes or ([1, 4] if truth else [1])]
    if sizes is None or len(sizes) == 1:
        return [(args.window, args.window_size, None)]
    return [(f"{args.window}{size}", size, None) for size in sizes]


def has_ground_truth(data, fmt, options: dict | None = None) -> bool:
    from envs.dataset import resolve_data

    return any(source.reader().flow_timestamps() is not None
               for source in resolve_data(data, format=fmt, options=options))


def check_folder_unused(folder: Path, option: str, overwrite: bool) -> None:
    """A folder this command fills (pictures, a DSEC submission) must not hold files of an earlier
    run unless ``overwrite``: FileExistsError naming the option and the folder."""
    if not overwrite and folder.is_dir() and any(folder.iterdir()):
        raise FileExistsError(f"{option}: {folder} holds files of an earlier run; pass --overwrite to replace them, "
                              "or write elsewhere")


def main(argv=None) -> int:
    args = parse_options(EvaluateOptions, argv, build_parser())
    args.set_threads()
    if args.refine_accept is not None and not args.refine:
        raise SystemExit("--refine-accept gates a refinement: give --refine K too")
    if args.split is not None and args.split != "dt" and not (args.split.isdigit() and int(args.split) >= 1):
        raise SystemExit(f"--split must be a number of sub-windows >= 1 or 'dt', got {args.split!r}")
    if args.split == "dt" and args.window != "frames" and not args.mvsec:
        raise SystemExit(f"--split dt steps once per ground-truth interval of frame windows; with --window {args.window} "
                         "give the number of sub-windows, --split N")
    if args.mirror is not None and args.mirror not in MIRROR_SETS:
        raise SystemExit(f"--mirror takes the number of copies, one of {sorted(MIRROR_SETS)}; got {args.mirror}")
    if args.dsec_submission and not args.dsec_test_timestamps:
        raise SystemExit("--dsec-submission needs --dsec-test-timestamps (the windows and file indices to write)")
    out = Path(args.out)
    json_path = Path(args.json) if args.json else out / "results.json"
    inputs = [("recording", path) for path in args.data] + [("checkpoint", path) for path in args.checkpoint]
    with contextlib.ExitStack() as claims:  # every output claimed before any work (envs.outputs)
        table_out = claims.enter_context(Output(out / "table.md", inputs=inputs, overwrite=args.overwrite, option="--out"))
        json_out = claims.enter_context(Output(json_path, inputs=inputs, overwrite=args.overwrite,
                                               option="--json" if args.json else "--out"))
        if args.pictures or args.animate:
            check_folder_unused(out / "pictures", "--out", args.overwrite)
        if args.dsec_submission:
            check_folder_unused(Path(args.dsec_submission), "--dsec-submission", args.overwrite)
        table, per_setting = evaluate_settings(args)
        table_out.write_text(table + "\n")
        json_out.write_text(results_json(per_setting) + "\n")
    print(table)
    print("\n" + TABLE_LEGEND)
    print(f"\nwrote {out / 'table.md'}, {json_path}" + (f" and pictures in {out / 'pictures'}" if args.pictures else ""))
    return 0


def evaluate_settings(args) -> tuple[str, dict]:
    """Every table of the command: (the Markdown tables, {setting key: {row name: results}})."""
    out = Path(args.out)
    policies = build_policies(args)
    data = args.data[0] if len(args.data) == 1 else args.data
    settings = protocol_settings(args, data)
    per_setting: dict[str, dict] = {}
    tables = []
    for key, size, protocol in settings:
        if args.mvsec:
            runs = mvsec_runs(Path(args.mvsec), protocol)
        elif protocol is not None:  # DSEC
            options = {**args.data_options(), **({"flow_dir": args.dsec_flow} if args.dsec_flow else {})}
            runs = [(data, args.format, options, protocol.windows, protocol.scorer)]
        else:
            runs = [(data, args.format, args.data_options(), None, None)]
        named = {name: [] for name in policies}
        if args.split == "dt" or default_mode_split(args):  # one sub-window per ground-truth interval of this table
            for policy in policies.values():
                for layer in (policy, getattr(policy, "policy", None)):
                    if isinstance(layer, SubWindowPolicy):
                        layer.splits = size
        sinks = dsec_sinks(args, protocol, policies) if args.dsec_submission else {}
        for run_data, fmt, options, windows_fn, scorer_fn in runs:
            for name, policy in policies.items():
                pictures = out / "pictures" / key / name.replace(" ", "_") if args.pictures or args.animate else None
                named[name] += evaluate(
                    policy, run_data, window=args.window, window_size=size, crop=args.crop, dt_ratio=args.dt_ratio,
                    data_options=options, windows_fn=windows_fn, max_windows=args.max_windows, pictures_dir=pictures,
                    pictures_per_sequence=args.pictures, animation_windows=args.animate,
                    progress=not args.no_progress, data_format=fmt, scorer_fn=scorer_fn, flow_sink=sinks.get(name),
                )
        per_setting[key] = named
        title = protocol.describe() if protocol is not None else f"windows of {windowing_of(named)}"
        tables.append(results_table(named, title=title))
        if args.protocol == "dsec":
            from agents.benchmarks import dsec_table

            tables.append(dsec_table(named, title=f"{title}: the benchmark's scores"))
        for name, sink in sinks.items():
            print(f"[dsec] {name}: wrote {len(sink.written)} PNGs under {sink.out_dir}"
                  + (f" ({sink.clipped} pixels clipped to the 16-bit range)" if sink.clipped else ""))
    return "\n\n".join(tables), per_setting


if __name__ == "__main__":
    sys.exit(main())
