"""Convert a recording in any supported format to the project h5 format.

    python scripts/convert.py INPUT OUTPUT.h5 [--format mvsec|dsec|hagenaars|ecd-text|aedat4|evflow-h5]
        [--crop center256 | --crop TOP LEFT H W]  (MVSEC)   [--flow-dir DIR --flow-timestamps FILE] (DSEC)
        [--sensor-size H W | auto] (text; RAW / DAT without geometry)
        [--flow-dt 1] [--no-flow] [--no-frames] [--chunk-events N] [--overwrite]

The format is detected from the file unless --format is given. Events are streamed a chunk at a
time with a progress bar; the output appears under its final name only when complete
(envs.readers.convert.convert_recording). An existing OUTPUT is refused unless --overwrite is
given; OUTPUT may never be INPUT itself (nor a link to it), nor a file another process is writing
now (envs.outputs.Output). Numbers are checked when parsed; a user error prints one line
(``error: ...``) and exits 2 (agents.commands.cli; EVFLOW_DEBUG=1 shows the traceback).
"""

from __future__ import annotations

import argparse
import os
import sys

from agents.options import SENSOR_SIZE_HELP, SensorSize, positive_int
from envs.outputs import Output
from envs.readers import FORMATS, open_recording
from envs.readers.convert import convert_recording


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("input", help="recording file or folder")
    parser.add_argument("output", help="project h5 file to write")
    parser.add_argument("--format", choices=FORMATS, default=None, help="input format (default: detect)")
    parser.add_argument("--crop", nargs="+", default=None, help="MVSEC crop: center256 or TOP LEFT HEIGHT WIDTH")
    parser.add_argument("--flow-dir", default=None, help="DSEC: folder of the flow PNGs")
    parser.add_argument("--flow-timestamps", default=None, help="DSEC: forward_timestamps.txt")
    parser.add_argument("--no-rectify", action="store_true", help="DSEC: keep the raw (unrectified) pixels")
    parser.add_argument("--sensor-size", action=SensorSize, default=None, help=SENSOR_SIZE_HELP)
    parser.add_argument("--flow-dt", type=positive_int, default=1, help="grid steps per stored ground-truth map")
    parser.add_argument("--no-flow", action="store_true", help="do not store ground truth")
    parser.add_argument("--no-frames", action="store_true", help="do not store frames")
    parser.add_argument("--chunk-events", type=positive_int, default=1 << 20, help="events per read/write step (> 0)")
    parser.add_argument("--overwrite", action="store_true", help="replace OUTPUT if it exists (never the input itself)")
    args = parser.parse_args(argv)

    options = {}
    if args.crop:
        options["crop"] = args.crop[0] if len(args.crop) == 1 else tuple(int(v) for v in args.crop)
    if args.flow_dir:
        options["flow_dir"] = args.flow_dir
    if args.flow_timestamps:
        options["flow_timestamps"] = args.flow_timestamps
    if args.no_rectify:
        options["rectify"] = False
    if args.sensor_size is not None:
        options["sensor_size"] = args.sensor_size
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
