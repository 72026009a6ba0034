"""Optical flow for a recording: every window's flow to an h5 file, a preview animation (events,
colour-coded flow, the flow at the events and the colour wheel with its scale; --arrows: sparse
arrows too), and a summary against zero flow.

Examples:
  python scripts/predict.py recording.raw                                # shipped model, 33 ms windows
  python scripts/predict.py recording.dat --window time --window-size 20000 --start 5 --end 15
  python scripts/predict.py rec.h5 --model runs/mgr/checkpoint.pt --per-event --device cuda
  python scripts/predict.py rec.h5 --model mypkg.models:build          # an (untrained) plug-in
  python scripts/predict.py old_camera.dat --sensor-size 480 640         # a header without geometry

--model: a shipped model name (agents/weights/, default the project's default model), a
checkpoint file, or a registry name / package.module:factory. Recordings in any supported
format (envs/readers: Prophesee RAW / DAT, AEDAT4, MVSEC, DSEC, project h5...). Windows as in
the env: ground-truth aligned frames where the recording has a ground-truth grid, else time
windows; the recurrent state is carried from window to window. See agents/predict.py for the
output layout.

Outputs (--out, --video, --json) are claimed before any work (envs.outputs.Output): never the
recording, never an existing file without --overwrite, never one another process is writing, and
a folder that cannot be written fails at once. Numbers are checked when parsed; a user error
prints one line (``error: ...``) and exits 2 (agents.commands.cli; EVFLOW_DEBUG=1: traceback).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import sys
from pathlib import Path

from agents.options import (
    SENSOR_SIZE_HELP,
    SensorSize,
    non_negative_float,
    non_negative_int,
    positive_float,
    positive_int,
)
from agents.predict import load_policy, predict, summary_dict, summary_table
from envs.outputs import Output


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("recording", help="recording file (or folder / synthetic split, with --sequence)")
    p.add_argument("--model", default=None, help="shipped name, checkpoint file, or registry name / package.module:factory")
    p.add_argument("--width", default="cpu", help="width of an untrained registry model")
    p.add_argument("--out", default=None, help="flow h5 to write (default: runs/predict/<recording>.flow.h5)")
    p.add_argument("--video", default=None, help="preview path, .gif or .mp4 (default: beside --out, .gif)")
    p.add_argument("--no-video", action="store_true")
    p.add_argument("--overwrite", action="store_true",
                   help="replace --out, --video and --json if they exist (never the recording itself)")
    p.add_argument("--video-frames", type=positive_int, default=150, help="windows shown, spread over the run")
    p.add_argument("--fps", type=positive_float, default=10.0)
    p.add_argument("--arrows", action="store_true", help="preview: also sparse arrows over the flow at the events")
    p.add_argument("--window", default="frames", choices=["frames", "time", "count"],
                   help="frames: ground-truth aligned where the recording has a grid, else time windows of --no-gt-window")
    p.add_argument("--no-gt-window", type=positive_int, default=33_333, help="us; frames mode on a recording without ground truth")
    p.add_argument("--window-size", type=positive_int, default=None,
                   help="frames: grid steps (1); time: us (10000); count: events (15000)")
    p.add_argument("--start", type=non_negative_float, default=None, help="seconds from the recording's start")
    p.add_argument("--end", type=positive_float, default=None, help="seconds from the recording's start")
    p.add_argument("--crop", type=non_negative_int, nargs="+", default=None, help="H W (centred) or TOP LEFT H W")
    p.add_argument("--sequence", default="0", help="which recording of a folder / split (index or name)")
    p.add_argument("--format", default=None, help="force a reader (see envs.readers.FORMATS)")
    p.add_argument("--sensor-size", action=SensorSize, default=None, help=SENSOR_SIZE_HELP)
    p.add_argument("--split", type=positive_int, default=1, metavar="N",
                   help="step the network through N equal sub-windows of each window and compose their flows "
                        "(long windows of fast motion; N network steps per window)")
    p.add_argument("--per-event", action="store_true", help="also store the flow at every event")
    p.add_argument("--json", default=None, help="also write the summary as JSON here")
    p.add_argument("--device", default="cpu", help="cpu, cuda, cuda:1...")
    p.add_argument("--threads", type=positive_int, default=None,
                   help="torch CPU threads (default: torch's choice; 1 on a busy machine)")
    p.add_argument("--no-progress", action="store_true")
    return p


def main(argv=None) -> int:  # opens as the other commands do: parse, then set torch's threads
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.start is not None and args.end is not None and args.end <= args.start:
        parser.error(f"--end {args.end} must be after --start {args.start} (seconds from the recording's start)")
    if args.threads:
        import torch

        torch.set_num_threads(args.threads)
    stem = Path(args.recording).name.split(".")[0] or "recording"
    out = Path(args.out) if args.out else Path("runs") / "predict" / f"{stem}.flow.h5"
    video = None if args.no_video else (Path(args.video) if args.video else out.with_name(out.name.split(".")[0] + ".gif"))
    sequence = int(args.sequence) if args.sequence.isdigit() else args.sequence
    # --json is claimed first (envs.outputs), so a bad path fails before the run; --out and
    # --video are claimed by predict() before it opens the recording
    json_out = Output(args.json, inputs=[("recording", args.recording)], overwrite=args.overwrite,
                      option="--json") if args.json else None
    with json_out or contextlib.nullcontext():
        policy, provenance = load_policy(args.model, device=args.device, width=args.width)
        result = predict(
            policy, args.recording, out, window=args.window, window_size=args.window_size, start_s=args.start,
            end_s=args.end, crop=args.crop, sequence=sequence, data_format=args.format, per_event=args.per_event,
            data_options={"sensor_size": args.sensor_size} if args.sensor_size is not None else None,
            video=video, video_fps=args.fps, video_frames=args.video_frames, video_arrows=args.arrows, provenance=provenance,
            no_gt_window_us=args.no_gt_window, progress=not args.no_progress, overwrite=args.overwrite, split=args.split,
        )
        name = provenance.get("name") or provenance.get("path") or "model"
        print(summary_table(result, name=str(name)))
        print(f"\n{result.windows} windows, {result.events} events in {result.seconds:.1f} s "
              f"({result.windows_per_second:.1f} windows/s)")
        print(f"wrote {result.path}" + (f" and {result.video}" if result.video else ""))
        if json_out:
            json_out.write_text(json.dumps({"model": provenance, **summary_dict(result)}, indent=2, default=str) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
