"""Convert a recording in any supported format to the project h5 format, or its events to numpy.

    python scripts/convert.py INPUT OUTPUT.h5 [--format mvsec|dsec|hagenaars|ecd-text|aedat4|evflow-h5|numpy]
    python scripts/convert.py INPUT OUTPUT.npy   # events alone: a structured array x, y, t (us), p (tonic's layout)
    python scripts/convert.py INPUT OUTPUT.npz   # the same as 'events', with 'sensor_size' (H, W)
        [--crop center256 | --crop TOP LEFT H W]  (MVSEC)   [--flow-dir DIR --flow-timestamps FILE] (DSEC)
        [--sensor-size H W | auto] (text; RAW / DAT without geometry)
        [--flow-dt 1] [--no-flow] [--no-frames] [--chunk-events N] [--overwrite]

The format is detected from the file unless --format is given. Events are streamed a chunk at a
time with a progress bar; the output appears under its final name only when complete
(envs.readers.convert.convert_recording). An existing OUTPUT is refused unless --overwrite is
given; OUTPUT may never be INPUT itself (nor a link to it), nor a file another process is writing
now (envs.outputs.Output). Numbers are checked when parsed; a user error prints one line
(``error: ...``) and exits 2 (evflow_cli.commands.cli; EVFLOW_DEBUG=1 shows the traceback).
"""

from __future__ import annotations

import argparse
import os
import sys
from dataclasses import dataclass

from agents.options import RecordingOptions, command_parser, option, options_from_args, positive_int
from envs.outputs import Output
from envs.readers import open_recording
from envs.readers.convert import convert_recording


@dataclass(kw_only=True)
class ConvertOptions(RecordingOptions):
    """What scripts/convert.py reads and writes (one option per field; the recordings group:
    agents.options)."""

    input: str = option(positional=True)
    """recording file or folder"""
    output: str = option(positional=True)
    """project h5 file to write"""
    crop: list[str] | None = None
    """MVSEC crop: center256 or TOP LEFT HEIGHT WIDTH"""
    flow_dir: str | None = None
    """DSEC: folder of the flow PNGs"""
    flow_timestamps: str | None = None
    """DSEC: forward_timestamps.txt"""
    no_rectify: bool = False
    """DSEC: keep the raw (unrectified) pixels"""
    flow_dt: int = option(1, type=positive_int)
    """grid steps per stored ground-truth map"""
    no_flow: bool = False
    """do not store ground truth"""
    no_frames: bool = False
    """do not store frames"""
    chunk_events: int = option(1 << 20, type=positive_int)
    """events per read/write step (> 0)"""
    overwrite: bool = False
    """replace OUTPUT if it exists (never the input itself)"""


def build_parser() -> argparse.ArgumentParser:
    return command_parser(ConvertOptions, __doc__)


def main(argv=None) -> int:
    args = options_from_args(ConvertOptions, build_parser().parse_args(argv))
    options = {}
    if args.crop:
        options["crop"] = args.crop[0] if len(args.crop) == 1 else tuple(int(v) for v in args.crop)
    if args.flow_dir:
        options["flow_dir"] = args.flow_dir
    if args.flow_timestamps:
        options["flow_timestamps"] = args.flow_timestamps
    if args.no_rectify:
        options["rectify"] = False
    options.update(args.data_options())
    # OUTPUT claimed before the input is opened (a Prophesee file is indexed on open): a bad OUTPUT
    # fails at once
    claim = Output(args.output, inputs=[("recording", args.input)], overwrite=args.overwrite)
    with claim, open_recording(args.input, args.format, **options) as reader:
        print(reader, file=sys.stderr)
        out = convert_recording(
            reader, claim, chunk_events=args.chunk_events, flow_dt=None if args.no_flow else args.flow_dt,
            frames=not args.no_frames, progress=True, source=os.path.abspath(args.input), overwrite=args.overwrite,
        )
    print(out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
