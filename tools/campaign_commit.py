#!/usr/bin/env python
"""Commit a campaign's state (and its exported weights) to git; the product's commands never do.

  python tools/campaign_commit.py mgr-devval                 # agents/campaigns/mgr-devval + its export
  python tools/campaign_commit.py mgr-devval --from OUT      # first take a GPU leg's output folder in
  python tools/campaign_commit.py --ablations                # the ablations' record (docs/ablations, with the
                                                             # slim states of stages in progress)

A campaign commit holds its folder (campaign.json, state.pt, curve.jsonl, curve.png,
reference.json) and agents/weights/EXPORT.pt/.json when they changed. It refuses a state over the
campaign's budget, more than three state commits within one stretch of training, and a commit
that would take the round's growth of the repository past 15 MB (tools/repo_growth.py; --force
to override either).
--from OUT: OUT is what scripts/device_train.sh wrote (OUT/campaigns/NAME, OUT/weights); it is
copied in only when its state is further along than the local one.
"""

from __future__ import annotations

import argparse
import shutil
import subprocess
import sys
import zlib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from evflow_cli.campaign import Campaign  # noqa: E402
from tools.repo_growth import ROUND_BUDGET, added_objects, round_start  # noqa: E402

MAX_STATE_COMMITS = 3


def _packed(path: Path) -> int:
    """About what git adds for the file: its zlib-compressed size."""
    return len(zlib.compress(path.read_bytes(), 6))


def git(*args: str, check: bool = True) -> str:
    return subprocess.run(["git", *args], cwd=ROOT, check=check, capture_output=True, text=True).stdout


def take_in(campaign: Campaign, source: Path) -> None:
    other = Campaign(campaign.name, source / "campaigns")
    if not other.state_path.exists():
        raise SystemExit(f"{source}: no campaigns/{campaign.name}/state.pt (not a device leg's output?)")
    if (campaign.state_step() or 0) >= (other.state_step() or 0):
        raise SystemExit(f"{source}: its state (step {other.state_step()}) is not past the local one "
                         f"(step {campaign.state_step()}); nothing taken in")
    for path in other.dir.iterdir():
        shutil.copy2(path, campaign.dir / path.name)
    export = campaign.spec().export
    for suffix in (".pt", ".json"):
        weights = source / "weights" / f"{export}{suffix}"
        if weights.exists():
            shutil.copy2(weights, ROOT / "agents" / "weights" / weights.name)
    print(f"took in step {other.state_step()} from {source}")


def commit_campaign(name: str, force: bool) -> None:
    campaign = Campaign(name)
    spec = campaign.spec()
    size = campaign.state_path.stat().st_size
    if size > spec.state_budget_mb * 2**20:
        raise SystemExit(f"{campaign.state_path}: {size / 2**20:.1f} MB, over the budget of {spec.state_budget_mb} MB")
    progress = campaign.progress()
    stretch = progress.get("stretches", 0)
    done = [s for s in git("log", "--format=%s", "--", str(campaign.state_path.relative_to(ROOT))).splitlines()
            if s.startswith(f"campaign {name}: stretch {stretch},")]
    weights = ROOT / "agents" / "weights" / f"{spec.export}.pt"
    per_commit = _packed(campaign.state_path) + (_packed(weights) if weights.exists() else 0)
    if len(done) >= MAX_STATE_COMMITS and not force:
        raise SystemExit(f"campaign {name}: already {len(done)} state commits in stretch {stretch} (at most "
                         f"{MAX_STATE_COMMITS}; --force to commit anyway)")
    grown = sum(size for size, _, _ in added_objects(round_start()))
    if grown + per_commit > ROUND_BUDGET and not force:
        raise SystemExit(f"campaign {name}: this round has added {grown / 2**20:.1f} MB to the repository and this "
                         f"commit adds about {per_commit / 2**20:.1f} MB more, past the {ROUND_BUDGET / 2**20:.0f} MB a "
                         "round may add (python tools/repo_growth.py); keep the curve and recipe only, or --force")
    paths = [str(p.relative_to(ROOT)) for p in campaign.dir.iterdir() if p.is_file()]
    paths += [f"agents/weights/{spec.export}{s}" for s in (".pt", ".json") if (ROOT / "agents" / "weights" /
                                                                             f"{spec.export}{s}").exists()]
    git("add", *paths)
    best = campaign.best(spec.mode)  # among the rows scored as the campaign scores now
    message = (f"campaign {name}: stretch {stretch}, step {campaign.state_step()}, "
               f"{progress.get('wall_s', 0) / 3600:.2f} training hours"
               + (f"; best validation {best['score']:.4f} at step {best['step']}" if best else ""))
    out = subprocess.run(["git", "commit", "-q", "-m", message, "--", *paths], cwd=ROOT, capture_output=True, text=True)
    print(message if out.returncode == 0 else (out.stdout + out.stderr).strip())


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("name", nargs="?", help="the campaign (agents/campaigns/NAME)")
    p.add_argument("--from", dest="source", type=Path, default=None, help="a device leg's output folder to take in")
    p.add_argument("--ablations", action="store_true", help="commit the ablations' record (docs/ablations)")
    p.add_argument("--force", action="store_true", help="commit past the per-stretch limit")
    args = p.parse_args(argv)
    if args.ablations:
        git("add", "docs/ablations")
        rows = ROOT / "docs" / "ablations" / "rows.jsonl"
        count = len(rows.read_text().splitlines()) if rows.exists() else 0
        states = sorted(p.stem for p in (ROOT / "docs" / "ablations" / "unfinished").glob("*.pt"))
        message = f"Ablations: {count} finished runs (rows, tables, curves)"
        if states:
            message += f"; stages kept in progress: {', '.join(states)}"
        subprocess.run(["git", "commit", "-q", "-m", message, "--", "docs/ablations"], cwd=ROOT, check=False)
        return 0
    if not args.name:
        p.error("name a campaign, or --ablations")
    if args.source:
        take_in(Campaign(args.name), args.source)
    commit_campaign(args.name, args.force)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
