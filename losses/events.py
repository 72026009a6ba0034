"""A batch of event windows as padded torch tensors (docs/method.md, "Conventions").

Every field is a ``(B, N)`` tensor; windows shorter than the longest one are padded with
``mask == False`` entries (x = y = tau = 0, p = +1) that every loss ignores.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, NamedTuple, Sequence

import numpy as np
import torch

__all__ = ["EventBatch"]


def _window_fields(w, b: int):
    """x, y, t, p (flat numpy arrays) and int t_start, t_end of window ``b``: a Window's
    attributes (``w.events.x``, ``w.t_start``, ...), or a dict's keys."""
    events = getattr(w, "events", None)
    if events is not None:
        x, y, t, p = (np.asarray(getattr(events, k)).reshape(-1) for k in ("x", "y", "t", "p"))
        return x, y, t, p, int(w.t_start), int(w.t_end)
    if not isinstance(w, Mapping):
        raise ValueError(f"window {b}: expected a Window (or a dict of x, y, t, p, t_start, t_end), "
                         f"got {type(w).__name__}")
    try:
        x, y, t, p = (np.asarray(w[k]).reshape(-1) for k in ("x", "y", "t", "p"))
        return x, y, t, p, int(w["t_start"]), int(w["t_end"])
    except KeyError as e:
        raise ValueError(f"window {b}: missing field {e.args[0]!r}") from None


class EventBatch(NamedTuple):
    """B event windows, padded to a common length N.

    x:    (B, N) float, column in pixels (integer for raw events, fractional when rectified).
    y:    (B, N) float, row in pixels.
    tau:  (B, N) float, normalised time ``(t - t_start) / (t_end - t_start)`` in [0, 1]
          (unitless; 1 is accepted for an event stamped exactly ``t_end``).
    p:    (B, N) float, polarity in {-1, +1}; ``p > 0`` is ON.
    mask: (B, N) bool, True for real events, False for padding.
    """

    x: torch.Tensor
    y: torch.Tensor
    tau: torch.Tensor
    p: torch.Tensor
    mask: torch.Tensor

    @property
    def batch_size(self) -> int:
        return int(self.x.shape[0])

    @property
    def num_slots(self) -> int:
        """N, the padded length (not the number of valid events)."""
        return int(self.x.shape[1])

    def zero_padding(self) -> "EventBatch":
        """The batch with zeros in the padding slots' x, y and tau (mask False), whatever they held:
        the torch path computes every slot (the compiled kernels skip padding), and a NaN there
        would become an out-of-range splat index (a device-side assert on CUDA)."""
        padding = ~self.mask
        return self._replace(x=self.x.masked_fill(padding, 0), y=self.y.masked_fill(padding, 0),
                             tau=self.tau.masked_fill(padding, 0))

    def to(self, device=None, dtype: torch.dtype | None = None) -> "EventBatch":
        """Move to ``device``; cast the float fields (not ``mask``) to ``dtype`` if given."""
        f = lambda a: a.to(device=device, dtype=dtype)  # noqa: E731
        return EventBatch(f(self.x), f(self.y), f(self.tau), f(self.p), self.mask.to(device))

    @classmethod
    def from_windows(
        cls,
        windows: Sequence[Any],
        device=None,
        dtype: torch.dtype = torch.float32,
    ) -> "EventBatch":
        """Pad a list of windows into one batch.

        windows: list of B windows (:class:`envs.windows.Window`: ``window.events`` with ``x``,
            ``y`` (N_b,) pixels, ``t`` (N_b,) int64 microseconds, ``p`` (N_b,) polarity ({-1,+1},
            {0,1} or bool; ``p > 0`` is ON) and ints ``window.t_start``, ``window.t_end``
            (microseconds, ``t_end > t_start``)); a plain dict with those six keys is taken too
            (events built by hand, no ``Events`` behind them). N_b may be 0.
        Returns a batch padded to N = max N_b (N = 0 if every window is empty).

        Every t must lie in the closed interval [t_start, t_end]: the window is half-open, but an
        event stamped exactly t_end (as count windows produce) is accepted as tau = 1.
        Raises ValueError for an empty list, and, naming the window index, for t outside
        [t_start, t_end], t_end <= t_start, non-finite x/y, or fields of different lengths.
        """
        if len(windows) == 0:
            raise ValueError("EventBatch.from_windows: empty batch (no windows given)")
        cols = []
        for b, w in enumerate(windows):
            x, y, t, p, t_start, t_end = _window_fields(w, b)
            n = x.shape[0]
            if not (y.shape[0] == t.shape[0] == p.shape[0] == n):
                raise ValueError(
                    f"window {b}: fields x, y, t, p have different lengths "
                    f"{x.shape[0]}, {y.shape[0]}, {t.shape[0]}, {p.shape[0]}"
                )
            if t_end <= t_start:
                raise ValueError(f"window {b}: t_end ({t_end}) must be > t_start ({t_start})")
            t = t.astype(np.int64)
            outside = (t < t_start) | (t > t_end)
            if outside.any():
                i = int(np.flatnonzero(outside)[0])
                raise ValueError(
                    f"window {b}: event {i} has t = {int(t[i])} us outside the window "
                    f"[{t_start}, {t_end}]"
                )
            xf, yf = x.astype(np.float64), y.astype(np.float64)
            if not (np.isfinite(xf).all() and np.isfinite(yf).all()):
                raise ValueError(f"window {b}: x or y holds NaN or inf")
            tau = (t - t_start).astype(np.float64) / float(t_end - t_start)
            pol = np.where(p > 0, 1.0, -1.0) if p.dtype != np.bool_ else np.where(p, 1.0, -1.0)
            cols.append((xf, yf, tau, pol))
        n_max = max(c[0].shape[0] for c in cols)
        B = len(cols)
        arr = np.zeros((4, B, n_max), dtype=np.float64)
        arr[3] = 1.0
        mask = np.zeros((B, n_max), dtype=bool)
        for b, c in enumerate(cols):
            n = c[0].shape[0]
            for k in range(4):
                arr[k, b, :n] = c[k]
            mask[b, :n] = True
        t_arr = torch.from_numpy(arr).to(device=device, dtype=dtype)
        return cls(t_arr[0], t_arr[1], t_arr[2], t_arr[3], torch.from_numpy(mask).to(device))
