"""What the diagnosis tools share: their model and data options, the model they load, and their
report (a JSON file and its Markdown table beside it, each whole or not at all)."""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path

from envs.atomic import temporary_path


def add_model_options(p: argparse.ArgumentParser, *, max_windows: int, out: str) -> None:
    """--model, --data, --dt, --max-windows (0: all), --threads, --out."""
    p.add_argument("--model", default=None, help="a shipped name or a checkpoint file (default: the shipped default)")
    p.add_argument("--data", default="../shared/devval", help="recordings (file or folder) or a split name")
    p.add_argument("--dt", type=int, default=1, help="ground-truth intervals per window")
    p.add_argument("--max-windows", type=int, default=max_windows, help="per sequence (0: all)")
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--out", default=out, help="JSON path (the table also to .md)")


def check_model_options(p: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    if args.dt < 1 or args.max_windows < 0:
        p.error(f"--dt must be >= 1 and --max-windows >= 0, got {args.dt} and {args.max_windows}")


def load_named_policy(model: str | None):
    """(policy, the name its report gives it): a shipped name, or a checkpoint's path."""
    from evflow_cli.predict import load_policy

    policy, provenance = load_policy(model)
    return policy, provenance.get("name") or provenance.get("path") or model


def write_report(out: str | os.PathLike, report: dict, text: str) -> None:
    """OUT (the JSON of ``report``) and OUT with .md (``text``), each written whole or not at all."""
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    for path, content in ((out, json.dumps(report, indent=1)), (out.with_suffix(".md"), text + "\n")):
        tmp = temporary_path(path)
        tmp.write_text(content)
        os.replace(tmp, path)
    print(f"wrote {out} and {out.with_suffix('.md')}")
