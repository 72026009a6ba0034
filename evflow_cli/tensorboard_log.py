"""A training run's curves and pictures in TensorBoard (``scripts/train.py --logger tensorboard``).

OUT/metrics.jsonl stays the run's record (the docs' curves are drawn from it, a resume cuts it
back); this writes the same numbers to ``OUT/tensorboard/`` as they come, for watching a run:

- ``train/<key>``: every number of an optimizer step's line (loss, zero_flow_loss, model_hmc,
  lr, grad_norm, windows_per_s...), at that step;
- ``val/<key>``: a validation's numbers (``val_aee_model`` -> ``val/aee_model``...);
- ``val/flow``: a picture per validation (``agents.evaluation.window_panel``: events, predicted
  flow with the colour wheel, ground truth where present, warped events).

A resumed run starts its writer at the checkpoint's step (``purge_step``), so the steps a killed
run logged after its last checkpoint are hidden, as they are cut from metrics.jsonl; a new run
started with ``--overwrite`` (step 0) hides the earlier run's.

TensorBoard is an optional extra: ``pip install evflow-gym[tensorboard]``.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

__all__ = ["TensorBoardLog", "require_tensorboard"]


def require_tensorboard() -> None:
    """ImportError saying how to install TensorBoard when it is not installed."""
    try:
        import tensorboard  # noqa: F401
        from torch.utils.tensorboard import SummaryWriter  # noqa: F401
    except ImportError:
        raise ImportError("--logger tensorboard needs the 'tensorboard' package, which is not installed: "
                          "pip install evflow-gym[tensorboard] (or pip install tensorboard); "
                          "or log to OUT/metrics.jsonl only with --logger jsonl") from None


class TensorBoardLog:
    """One run's TensorBoard event files in ``folder`` (module docstring for the tags).

    start_step: the step the run starts from (a resume's checkpoint step; 0 for a new run):
    events an earlier writer logged at or after it are hidden."""

    def __init__(self, folder: str | os.PathLike, start_step: int = 0) -> None:
        require_tensorboard()
        from torch.utils.tensorboard import SummaryWriter

        self.folder = Path(folder)
        self._writer = SummaryWriter(log_dir=str(self.folder), purge_step=int(start_step))

    def scalars(self, row: dict, prefix: str) -> None:
        """Every number of a metrics line ``row`` (one holding ``step``) as ``prefix/<key>``; a
        key starting with ``prefix_`` loses it (``val_aee_model`` -> ``val/aee_model``)."""
        step = int(row["step"])
        for key, value in row.items():
            if key == "step" or isinstance(value, bool) or not isinstance(value, (int, float)):
                continue
            self._writer.add_scalar(f"{prefix}/{key.removeprefix(prefix + '_')}", float(value), step)

    def image(self, tag: str, rgb: np.ndarray, step: int) -> None:
        """rgb: (H, W, 3) uint8, e.g. a flow panel."""
        self._writer.add_image(tag, np.ascontiguousarray(rgb), int(step), dataformats="HWC")

    def flush(self) -> None:
        self._writer.flush()

    def close(self) -> None:
        self._writer.close()
