"""A ``torchrun`` entry for tests/test_distributed.py: scripts/train.py, recording on each rank
what every update rolled over (per window and env: sequence, bounds, a digest of the events) and
its loss, one line per update in OUT/windows-rank<R>.jsonl."""

from __future__ import annotations

import hashlib
import json
import os
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from agents import learner as learner_module  # noqa: E402
from agents.objectives import windows_from_info  # noqa: E402
from evflow_cli.commands import train  # noqa: E402


def _digest(window) -> str:
    data = b"".join(np.ascontiguousarray(getattr(window.events, key)).tobytes() for key in ("x", "y", "t", "p"))
    return hashlib.sha1(data).hexdigest()[:16]


def main(argv: list[str]) -> int:
    out = Path(argv[argv.index("--out") + 1])
    path = out / f"windows-rank{os.environ.get('RANK', '0')}.jsonl"
    seen: list[list] = []

    def recorded(info, num_envs):
        seen.append([[str(info["sequence"][i]), int(info["window"][i].t_start), int(info["window"][i].t_end),
                      _digest(info["window"][i])] for i in range(num_envs)])
        return windows_from_info(info, num_envs)

    update = learner_module.Learner.update

    def recording_update(self):
        seen.clear()
        stats = update(self)
        out.mkdir(parents=True, exist_ok=True)
        with open(path, "a") as log:
            log.write(json.dumps({"step": stats["step"], "loss": stats["loss"], "windows": seen}) + "\n")
        return stats

    learner_module.windows_from_info = recorded
    learner_module.Learner.update = recording_update
    return train.main(argv)


if __name__ == "__main__":
    train.exit_process(main(sys.argv[1:]))  # as scripts/train.py ends a rank
