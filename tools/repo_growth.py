#!/usr/bin/env python
"""How much a round of work has added to the repository: the bytes git stores for the objects
reachable from HEAD and not from the round's first commit (as packed or compressed on disk), and
the largest of them. A round may add at most 15 MB (ROUND_BUDGET); tools/campaign_commit.py
refuses a commit past it.

  python tools/repo_growth.py                  # since the last commit before today (UTC)
  python tools/repo_growth.py --since f0cf110  # since a given commit
"""

from __future__ import annotations

import argparse
import datetime
import subprocess
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
#: the most one round of work may add to the repository (bytes as git stores them)
ROUND_BUDGET = 15 * 2**20


def _git(*args: str, stdin: str | None = None, root: Path = ROOT) -> str:
    return subprocess.run(["git", *args], cwd=root, check=True, capture_output=True, text=True, input=stdin).stdout


def round_start(root: Path = ROOT) -> str | None:
    """The last commit before today (UTC), the round's base; None when every commit is today's."""
    today = datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%dT00:00:00Z")
    return _git("rev-list", "-1", f"--before={today}", "HEAD", root=root).strip() or None


def added_objects(since: str | None, root: Path = ROOT) -> list[tuple[int, str, str]]:
    """(bytes on disk, object id, path) of every object reachable from HEAD and not from
    ``since`` (None: every object), largest first."""
    listed = _git("rev-list", "--objects", "HEAD", *([f"^{since}"] if since else []), root=root).splitlines()
    paths = {line.split(" ", 1)[0]: (line.split(" ", 1) + [""])[1] for line in listed if line}
    if not paths:
        return []
    sizes = _git("cat-file", "--batch-check=%(objectname) %(objectsize:disk)", stdin="\n".join(paths) + "\n",
                 root=root)
    rows = []
    for line in sizes.splitlines():
        oid, size = line.split()
        rows.append((int(size), oid, paths[oid]))
    return sorted(rows, reverse=True)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--since", default=None, help="the round's base commit (default: the last one before today)")
    p.add_argument("--top", type=int, default=8, help="how many of the largest objects to list")
    args = p.parse_args(argv)
    since = args.since or round_start()
    rows = added_objects(since)
    total = sum(r[0] for r in rows)
    print(f"since {since[:10] if since else 'the first commit'}: {total / 2**20:.2f} MB added "
          f"({len(rows)} objects; budget {ROUND_BUDGET / 2**20:.0f} MB a round)")
    for size, _, path in rows[: args.top]:
        print(f"  {size / 2**20:8.2f} MB  {path or '(commit or tree)'}")
    return 0 if total <= ROUND_BUDGET else 1


if __name__ == "__main__":
    raise SystemExit(main())
