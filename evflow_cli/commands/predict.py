"""Optical flow for a recording: every window's flow to an h5 file, a preview animation (events,
colour-coded flow, the flow at the events and the colour wheel with its scale; --arrows: sparse
arrows too), and a summary against zero flow.

Examples:
  python scripts/predict.py recording.raw                                # shipped model, 33 ms windows
  python scripts/predict.py rec.h5 --window-size 4                       # 4-frame windows, 4 network steps each
  python scripts/predict.py recording.dat --window time --window-size 20000 --start 5 --end 15
  python scripts/predict.py rec.h5 --model runs/mgr/checkpoint.pt --per-event --device cuda
  python scripts/predict.py rec.h5 --model mypkg.models:build          # an (untrained) plug-in
  python scripts/predict.py old_camera.dat --sensor-size 480 640         # a header without geometry
  python scripts/predict.py hd_camera.raw --coarse 2                     # 1280x720: the network on a 2x coarser grid

--model: a shipped model name (agents/weights/, default the project's default model), a
checkpoint file, or a registry name / package.module:factory. Recordings in any supported
format (envs/readers: Prophesee RAW / DAT, AEDAT4, MVSEC, DSEC, project h5...). Windows as in
the env: ground-truth aligned frames where the recording has a ground-truth grid, else time
windows; the recurrent state is carried from window to window. See evflow_cli/predict.py for the
output layout.

Outputs (--out, --video, --json) are claimed before any work (envs.outputs.Output): never the
recording, never an existing file without --overwrite, never one another process is writing, and
a folder that cannot be written fails at once. Numbers are checked when parsed; a user error
prints one line (``error: ...``) and exits 2 (evflow_cli.commands.cli; EVFLOW_DEBUG=1: traceback).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import sys
from dataclasses import dataclass
from pathlib import Path

from agents.options import (
    DeviceOptions,
    ModelWidth,
    Progress,
    RecordingOptions,
    Windows,
    check_choices,
    command_parser,
    non_negative_float,
    non_negative_int,
    option,
    options_from_args,
    positive_float,
    positive_int,
)
from agents.pretrained import default_finish, default_steps
from agents.wrappers.coarse import CoarsePolicy
from agents.wrappers.refine import FinishedPolicy, with_coarse
from envs.outputs import Output
from envs.windows import FALLBACK_INTERVAL_US
from evflow_cli.predict import load_policy, predict, summary_dict, summary_table


@dataclass(kw_only=True)
class PredictOptions(ModelWidth, Windows, RecordingOptions, DeviceOptions, Progress):
    """What scripts/predict.py runs on which recording, and what it writes (one option per field;
    the string under a field is its help; the shared groups: agents.options)."""

    recording: str = option(positional=True)
    """recording file (or folder / synthetic split, with --sequence)"""
    model: str | None = None
    """shipped name, checkpoint file, or registry name / package.module:factory"""
    plugin: str | None = option(None, metavar="MODULE:FACTORY")
    """with --model CHECKPOINT: the plug-in model (dotted path) the checkpoint names, trusted because you name it here (a checkpoint alone may only name a registered model)"""
    out: str | None = None
    """flow h5 to write (default: runs/predict/<recording>.flow.h5)"""
    video: str | None = None
    """preview path: .gif (one dithered palette), .png (animated PNG, lossless) or .mp4 (with imageio-ffmpeg); default: beside --out, .gif"""
    no_video: bool = False
    """no preview"""
    overwrite: bool = False
    """replace --out, --video and --json if they exist (never the recording itself)"""
    video_frames: int = option(150, type=positive_int)
    """windows shown, spread over the run"""
    video_width: int | None = option(None, type=positive_int)
    """the widest a preview tile is, in pixels (default: the sensor's width up to 640)"""
    flow_max: float | None = option(None, type=positive_float)
    """the preview's colour scale: pixels of flow at the colour wheel's rim, the same in every frame (default: the 99th percentile of the flow at the events over the frames shown)"""
    fps: float = option(10.0, type=positive_float)
    """frames per second of the preview"""
    arrows: bool = False
    """preview: also sparse arrows over the flow at the events"""
    no_gt_window: int = option(FALLBACK_INTERVAL_US, type=positive_int)
    """us; --window frames on a recording without a ground-truth grid"""
    start: float | None = option(None, type=non_negative_float)
    """seconds from the recording's start"""
    end: float | None = option(None, type=positive_float)
    """seconds from the recording's start"""
    crop: list[int] | None = option(None, type=non_negative_int)
    """H W (centred) or TOP LEFT H W"""
    sequence: str = "0"
    """which recording of a folder / split (index or name)"""
    no_finish: bool = False
    """the default model's proposal alone: skip the short solve on each window's events that its mode finishes the flow with (faster; docs/finish.md)"""
    coarse: int = option(1, type=positive_int, metavar="F")
    """the network on each window's events binned F x F pixels to one, its flow upsampled to the sensor (F^2 times fewer pixels; at F = 2 on a 1280x720 sensor 2.3x the windows/s, 4.7x with --no-finish, at a cost in accuracy: docs/performance.md; 1-16); the finish still solves on the sensor's pixels"""
    split: int | None = option(None, type=positive_int, metavar="N")
    """step the network through N equal sub-windows of each window and compose their flows (long windows of fast motion; N network steps per window); default: the default model's mode (agents/weights/default.json's split: one pass, or one step per ground-truth interval), 1 for any other model"""
    per_event: bool = False
    """also store the flow at every event"""
    score: str = option("100", metavar="N|all")
    """take the per-window metrics of the summary (L_HMC, FWL, RSAT, AEE) on N windows spread over the run, or on all (on a large sensor they cost more than the network); 0: none"""
    json: str | None = None
    """also write the summary as JSON here"""

    def __post_init__(self) -> None:
        check_choices(self)
        if self.coarse > 16:
            raise ValueError(f"--coarse takes a factor from 1 to 16, got {self.coarse}")
        if self.score != "all" and not self.score.isdigit():
            raise ValueError(f"--score takes a number of windows or 'all', got {self.score!r}")

    def score_windows(self) -> int | None:
        """--score as predict()'s score_windows (None: every window)."""
        return None if self.score == "all" else int(self.score)


def build_parser() -> argparse.ArgumentParser:
    return command_parser(PredictOptions, __doc__)


def main(argv=None) -> int:  # opens as the other commands do: parse, then set torch's threads
    parser = build_parser()
    args = options_from_args(PredictOptions, parser.parse_args(argv))
    if args.start is not None and args.end is not None and args.end <= args.start:
        parser.error(f"--end {args.end} must be after --start {args.start} (seconds from the recording's start)")
    if isinstance(args.window_size, list):
        parser.error(f"--window-size: predict runs one window size, got {' '.join(map(str, args.window_size))}")
    args.set_threads()
    stem = Path(args.recording).name.split(".")[0] or "recording"
    out = Path(args.out) if args.out else Path("runs") / "predict" / f"{stem}.flow.h5"
    video = None if args.no_video else (Path(args.video) if args.video else out.with_name(out.name.split(".")[0] + ".gif"))
    sequence = int(args.sequence) if args.sequence.isdigit() else args.sequence
    # --json is claimed first (envs.outputs), so a bad path fails before the run; --out and
    # --video are claimed by predict() before it opens the recording
    json_out = Output(args.json, inputs=[("recording", args.recording)], overwrite=args.overwrite,
                      option="--json") if args.json else None
    with json_out or contextlib.nullcontext():
        policy, provenance = load_policy(args.model, device=args.device, width=args.width, plugin=args.plugin)
        finish = default_finish() if args.model is None and args.split is None and not args.no_finish else []
        if finish:  # the default's mode: the network's flow finished by a short solve on each window
            policy = FinishedPolicy(policy, with_coarse(finish, args.coarse))
            provenance["default"]["finish"] = [f.label() + (f" up to {f.up_to_frames:g} frames" if f.up_to_frames else "")
                                               for f in policy.finishes]
        elif args.coarse > 1:
            policy = CoarsePolicy(policy, args.coarse)
        if args.coarse > 1:
            provenance["coarse"] = args.coarse
        split = args.split
        if split is None:
            split = default_steps(args.window, args.window_size, args.no_gt_window) if args.model is None else 1
        if "default" in provenance:
            provenance["default"]["split"] = split
        result = predict(
            policy, args.recording, out, window=args.window, window_size=args.window_size, start_s=args.start,
            end_s=args.end, crop=args.crop, sequence=sequence, data_format=args.format, per_event=args.per_event,
            data_options=args.data_options() or None,
            video=video, video_fps=args.fps, video_frames=args.video_frames, video_arrows=args.arrows, provenance=provenance,
            video_width=args.video_width, flow_max=args.flow_max, score_windows=args.score_windows(),
            no_gt_window_us=args.no_gt_window, progress=not args.no_progress, overwrite=args.overwrite, split=split,
        )
        name = provenance.get("name") or provenance.get("path") or "model"
        print(summary_table(result, name=str(name)))
        print(f"\n{result.windows} windows, {result.events} events in {result.seconds:.1f} s "
              f"({result.windows_per_second:.1f} windows/s); {result.where_the_time_goes()}")
        print(f"wrote {result.path}" + (f" and {result.video}" if result.video else ""))
        if json_out:
            json_out.write_text(json.dumps({"model": provenance, **summary_dict(result)}, indent=2, default=str) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
