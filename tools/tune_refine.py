#!/usr/bin/env python
"""Compare test-time refinement settings (agents/wrappers/refine.py, RefinedPolicy) of a shipped
model on a split: AEE, L_HMC and time per window at dt = 1 and dt = 4, first windows of every sequence.

    python tools/tune_refine.py --data synthetic-dr-val --max-windows 5 \\
        --refine fine:30:0 cmax:100:0 cmax:100:1 cmax:100:10 cmax:100:0:0.05

Each --refine is SOLVER:STEPS:PRIOR[:ACCEPT] (``RefinedPolicy(solver=, steps=, prior_weight=,
accept=)``; without ACCEPT the refined flow is always kept). Tune on
the selection split (synthetic-dr-val), never on synthetic-stress or a test split.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from compare_cmax import print_comparison  # noqa: E402

from agents.cmax import ContrastMaximisationPolicy  # noqa: E402
from agents.policy import RecurrentPolicy  # noqa: E402
from agents.pretrained import DEFAULT_PRETRAINED  # noqa: E402
from agents.wrappers import RefinedPolicy  # noqa: E402


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", nargs="+", default=["synthetic-dr-val"])
    p.add_argument("--pretrained", default=DEFAULT_PRETRAINED)
    p.add_argument("--max-windows", type=int, default=5, help="per sequence")
    p.add_argument("--dt", type=int, nargs="+", default=[1, 4])
    p.add_argument("--refine", nargs="+", default=["cmax:100:0"], help="SOLVER:STEPS:PRIOR[:ACCEPT], one row each")
    p.add_argument("--cmax", action="store_true", help="add the --cmax row (the solve from zero)")
    args = p.parse_args(argv)
    data = args.data[0] if len(args.data) == 1 else args.data
    network = RecurrentPolicy.from_pretrained(args.pretrained)
    rows: dict = {args.pretrained: network}
    for spec in args.refine:
        if spec.count(":") not in (2, 3):
            raise SystemExit(f"--refine {spec}: expected SOLVER:STEPS:PRIOR[:ACCEPT]")
        solver, steps, prior, *accept = spec.split(":")
        rows[f"refine {spec}"] = RefinedPolicy(network, solver=solver, steps=int(steps), prior_weight=float(prior),
                                               accept=float(accept[0]) if accept else None)
    if args.cmax:
        rows["contrast maximisation (no network)"] = ContrastMaximisationPolicy()
    rows["zero flow"] = None
    print_comparison(rows, data, args.dt, args.max_windows)
    return 0


if __name__ == "__main__":
    sys.exit(main())
