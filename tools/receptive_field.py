#!/usr/bin/env python
"""How far a flow network looks: the gradient of one output pixel's flow with respect to the input,
on random sparse event images (summed over a few), and over channels and time bins. Prints the extent where the
gradient is not zero (the theoretical receptive field, as far as it reaches in the frame) and the
radii that hold 50 / 90 / 99 % of its mass (the effective receptive field: what the trained
network actually reads).

    python tools/receptive_field.py --pretrained ev-mgrflownet-cpu-derived-cycle2

A zero input is not used: with no events most units sit at their bias and pass no gradient, and
the field looks a few pixels wide. ``--density`` sets the share of input cells holding an event
(+-1), ``--size`` the frame (the pixel read is its centre).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402
import torch  # noqa: E402


def gradient_map(model: torch.nn.Module, channels: int, size: int, density: float = 0.1, seed: int = 0) -> np.ndarray:
    """(size, size) float64: |d flow(centre) / d input| summed over the flow's two components and the
    input's channels, for a random input with ``density`` of its cells at +-1. ``model(x)`` returns
    the flow (B, 2, H, W) or a tuple whose first item is a list of flows (the last one is read)."""
    generator = torch.Generator().manual_seed(seed)
    events = torch.rand(1, channels, size, size, generator=generator) < density
    signs = torch.where(torch.rand(1, channels, size, size, generator=generator) < 0.5, -1.0, 1.0)
    x = (events.float() * signs).requires_grad_(True)
    with torch.enable_grad():
        out = model(x)
        flow = out[0][-1] if isinstance(out, tuple) else out
        flow[0, :, size // 2, size // 2].sum().backward()
    return x.grad.abs().sum(dim=(0, 1)).double().numpy()


def field_stats(grad: np.ndarray, fractions=(0.5, 0.9, 0.99)) -> dict:
    """The extent of the non-zero gradient (half-widths in rows and columns about the centre) and
    the radii holding the given fractions of its mass."""
    size = grad.shape[0]
    centre = size // 2
    rows, cols = np.nonzero(grad > 1e-6 * grad.max())
    yy, xx = np.mgrid[:size, :size]
    radius = np.hypot(yy - centre, xx - centre).ravel()
    order = np.argsort(radius, kind="stable")
    mass = np.cumsum(grad.ravel()[order])
    radii = {f: float(radius[order][np.searchsorted(mass, f * mass[-1])]) for f in fractions}
    half = max(centre - rows.min(), rows.max() - centre, centre - cols.min(), cols.max() - centre)
    return {"half_width": int(half), "radii": radii}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--pretrained", default=None, help="shipped model name (default: the default model)")
    p.add_argument("--size", type=int, default=320, help="frame size in pixels (default 320)")
    p.add_argument("--density", type=float, default=0.1, help="share of input cells with an event (default 0.1)")
    p.add_argument("--inputs", type=int, default=4, help="random inputs whose gradient maps are summed (default 4)")
    args = p.parse_args(argv)
    if not 0 < args.density <= 1:
        p.error(f"--density must be in (0, 1], got {args.density}")
    if args.inputs < 1 or args.size < 8:
        p.error(f"--inputs must be >= 1 and --size >= 8, got {args.inputs} and {args.size}")
    from agents.pretrained import load_pretrained

    model, info = load_pretrained(args.pretrained)
    model = model.float()
    for parameter in model.parameters():
        parameter.requires_grad_(False)
    grad = sum(gradient_map(model, model.in_channels, args.size, args.density, seed) for seed in range(args.inputs))
    stats = field_stats(grad)
    radii = ", ".join(f"{100 * f:g} %: {r:.0f} px" for f, r in stats["radii"].items())
    print(f"{info.get('name', args.pretrained or 'default')}: the gradient reaches {stats['half_width']} px from the pixel "
          f"(frame {args.size}); radii holding its mass: {radii}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
