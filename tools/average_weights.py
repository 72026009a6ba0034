#!/usr/bin/env python
"""Average the network weights of several checkpoints of one training line (stochastic weight
averaging over a constant-step-size trajectory): a new weights file to evaluate like any other.

    git show 2bd5a88:agents/weights/ev-mgrflownet-cpu-long-windows.pt > runs/avg/5462.pt
    python tools/average_weights.py runs/avg/5462.pt agents/weights/ev-mgrflownet-cpu-long-windows.pt \\
        agents/campaigns/mgr-long-windows/state.pt --out runs/avg/avg.pt
    python scripts/evaluate.py --checkpoint runs/avg/avg.pt --split dt --data ../shared/devval/*.h5 --window-size 1 4

Inputs are training checkpoints, campaign states or shipped weights files (agents/checkpoint.py's
format) of the same network (name and configuration); their floating-point tensors are averaged
in float32 (optionally weighted), integer buffers are taken from the first. The output is a
weights file (network only, float32) whose provenance names its sources and their steps. A
network with batch normalisation would need its statistics re-estimated after averaging; the
project's networks have none.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


from agents.checkpoint import load_checkpoint, save_checkpoint  # noqa: E402


def average_checkpoints(paths: list[Path], weights: list[float] | None = None) -> dict:
    """The first checkpoint's header (format, model name and configuration, step of the last) with
    its network replaced by the weighted mean of all networks. ValueError naming the file for a
    network of another name, configuration or set of parameters."""
    if not paths:
        raise ValueError("no checkpoints to average")
    weights = [1.0] * len(paths) if weights is None else [float(w) for w in weights]
    if len(weights) != len(paths) or any(w < 0 for w in weights) or sum(weights) <= 0:
        raise ValueError(f"--weights: one non-negative number per checkpoint ({len(paths)}), not all zero; got {weights}")
    payloads = [load_checkpoint(p) for p in paths]
    first = payloads[0]
    for path, payload in zip(paths[1:], payloads[1:]):
        for key in ("model_name", "model_config"):
            if payload.get(key) != first.get(key):
                raise ValueError(f"{path}: {key} {payload.get(key)!r}, the first checkpoint's is {first.get(key)!r}")
        if payload["model"].keys() != first["model"].keys():
            raise ValueError(f"{path}: other network parameters than {paths[0]}")
    total = sum(weights)
    model = {}
    for name, tensor in first["model"].items():
        if tensor.is_floating_point():
            model[name] = sum(w * p["model"][name].float() for w, p in zip(weights, payloads)) / total
        else:
            model[name] = tensor.clone()
    header = {key: first[key] for key in ("model_name", "model_config", "config") if key in first}
    sources = [{"file": str(p), "step": int(payload.get("step", -1)), "weight": w}
               for p, payload, w in zip(paths, payloads, weights)]
    return {**header, "model": model, "step": max(s["step"] for s in sources), "averaged_from": sources}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("checkpoints", nargs="+", type=Path, help="checkpoints, campaign states or weights files")
    parser.add_argument("--weights", type=float, nargs="+", default=None, help="one weight per checkpoint (default: equal)")
    parser.add_argument("--out", type=Path, required=True, help="the averaged weights file to write")
    args = parser.parse_args(argv)
    if args.out.exists():
        parser.error(f"{args.out} exists; delete it to write it again")
    try:
        averaged = average_checkpoints(args.checkpoints, args.weights)
    except (ValueError, OSError) as err:
        parser.error(str(err))
    save_checkpoint(args.out, averaged)  # atomic: a whole file or none
    steps = ", ".join(str(s["step"]) for s in averaged["averaged_from"])
    print(f"{args.out}: {averaged['model_name']} averaged over {len(args.checkpoints)} checkpoints (steps {steps})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
