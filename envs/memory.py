"""Events held in memory as recordings: a structured numpy array with fields ``x, y, t, p``
(tonic's layout; ``t`` in µs, ``p`` 0/1, -1/+1 or bool), a mapping of four arrays, or an
:class:`envs.events.Events`, with a sensor size. Accepted wherever a recording is::

    env = gymnasium.make("EventFlow-v0", data=events, sensor_size=(480, 640))
    flows, bounds = agents.predict_flow(events, sensor_size=(480, 640))

``sensor_size``: (height, width); a 3-tuple is tonic's ``(width, height, polarities)``; "auto" the
smallest known sensor holding the events (with a warning, ``envs.readers._common``).
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from envs.events import Events

__all__ = ["FIELDS", "is_event_data", "is_event_dataset", "dataset_sample_events", "events_from_memory",
           "sensor_size_of"]

FIELDS = ("x", "y", "t", "p")


def is_event_dataset(obj) -> bool:
    """True for a dataset of event recordings as tonic makes them (``tonic.datasets.*``, or any
    object with ``sensor_size``, ``__len__`` and ``__getitem__`` giving a sample): each sample is
    one recording, its events the sample itself or the first item of an ``(events, target)`` pair."""
    if isinstance(obj, (str, bytes, np.ndarray, Mapping, list, tuple, Events)):
        return False
    return hasattr(obj, "sensor_size") and hasattr(obj, "__len__") and hasattr(obj, "__getitem__")


def dataset_sample_events(dataset, index: int):
    """The events of sample ``index`` of a tonic-style dataset (:func:`is_event_dataset`)."""
    sample = dataset[index]
    return sample[0] if isinstance(sample, tuple) else sample


def is_event_data(obj) -> bool:
    """True for what :func:`events_from_memory` takes (not a path, a split name or a list of them)."""
    if isinstance(obj, Events):
        return True
    if isinstance(obj, np.ndarray):
        return obj.dtype.names is not None and set(FIELDS) <= set(obj.dtype.names)
    return isinstance(obj, Mapping) and set(FIELDS) <= set(obj)


def sensor_size_of(size, source: str = "events") -> tuple[int, int] | str:
    """(height, width) from ``size``: a pair as given, tonic's (width, height, polarities)
    turned round, or "auto". ValueError naming the problem otherwise."""
    if isinstance(size, str):
        if size != "auto":
            raise ValueError(f"{source}: sensor_size must be (height, width), tonic's (width, height, polarities) "
                             f"or 'auto', got {size!r}")
        return size
    if size is None:
        raise ValueError(f"{source}: events from memory need sensor_size=(height, width) (or 'auto', or tonic's "
                         "(width, height, polarities))")
    values = tuple(int(v) for v in size)
    if len(values) == 3:  # tonic: (W, H, P)
        return values[1], values[0]
    if len(values) != 2:
        raise ValueError(f"{source}: sensor_size must be (height, width) or tonic's (width, height, polarities), "
                         f"got {size!r}")
    return values


def events_from_memory(data, sensor_size, source: str = "events") -> Events:
    """The events of ``data`` (module docstring), checked as a file's are (``Events.create``:
    lengths, integer time stamps that never decrease, coordinates inside the sensor, polarity)."""
    if isinstance(data, Events):
        size = data.sensor_size if sensor_size is None else sensor_size_of(sensor_size, source)
        if size != "auto" and tuple(size) != tuple(data.sensor_size):
            raise ValueError(f"{source}: sensor_size {size} differs from the events' own {data.sensor_size}")
        return data
    if not is_event_data(data):
        raise TypeError(f"{source}: expected a structured array with fields {FIELDS}, a mapping of those four arrays or "
                        f"Events, got {type(data).__name__}")
    columns = {k: np.asarray(data[k]) for k in FIELDS}
    t = columns["t"]
    if t.dtype.kind == "f":
        if len(t) and not np.all(np.isfinite(t)):
            raise ValueError(f"{source}: field 't' holds NaN or infinite time stamps")
        if len(t) and not np.array_equal(t, np.round(t)):
            raise ValueError(f"{source}: field 't' must be whole microseconds (tonic's unit), got fractions "
                             "(seconds? multiply by 1e6 first)")
    size = sensor_size_of(sensor_size, source)
    if size == "auto":
        from envs.readers._common import auto_sensor_size

        size = auto_sensor_size(int(columns["x"].max(initial=-1)), int(columns["y"].max(initial=-1)), source)
    p = columns["p"]
    if p.dtype == bool:
        p = p.astype(np.int8)
    return Events.create(columns["x"], columns["y"], t, p, size, source=source)
