"""Named synthetic benchmark splits: fixed seeds, resolutions and motion ranges, simulated on
demand by :mod:`envs.simulator` and cached.

    from envs.synthetic import SPLITS, list_sequences, load_sequence
    reader = load_sequence("synthetic-test", 0)          # or by name: "synthetic-test-128-00"
    reader.flow_between(*reader.flow_timestamps()[:2])   # exact ground truth, 30 Hz grid

Splits (all 30 Hz frames; ``max_flow_px`` bounds the displacement of any visible point over
one frame interval, spread geometrically over each split, so windows range from sub-pixel to
~10 px):

- ``synthetic-train``: 32 sequences, 128x128, 2 s each, max_flow_px 0.5-14.
- ``synthetic-test``: 8 sequences at 128x128 and 3 at 256x256, 1 s each, max_flow_px 0.5-14.
- ``synthetic-mini``: 3 sequences, 64x64, 1 s each, max_flow_px 1, 3, 8 (tests and demos).
- ``synthetic-dr-train``: domain-randomised training data (:mod:`envs.simulator.randomize`):
  every scene, motion, sensor and size factor drawn per sequence; 1 s each, 64x64 to 260x346.
  256 sequences by name; ``synthetic-dr-train:N`` is the first N of the same endless series
  (any N; sequence i is the same whatever N, and shares its cache file).
- ``synthetic-dr-val``: 8 sequences of the training distribution with seeds no training
  sequence has: the validation that picks a training run's checkpoints (so not a test).
- ``synthetic-transfer-train`` / ``synthetic-transfer-val``: the same, drawn from
  ``TRANSFER_FACTORS`` (textured surfaces, slower cameras at the low end, sensor settings over
  real sensors' ranges); 256 / 8 sequences, ``synthetic-transfer-train:N`` like the above.
- ``synthetic-traffic``: held out: 4 sequences of 1.5 s (180x240 and 260x346) of a fixed camera
  watching 1-4 mostly small moving objects, with background activity and hot pixels
  (``TRAFFIC_FACTORS``): the case of a static DAVIS346 over a street.
- ``synthetic-stress``: held out, never for training or tuning: 4 groups of 3 sequences
  (1 s, native size), each with one factor group outside the training ranges: ``texture``
  (dots and plaid families), ``fast`` (camera 16-22, objects 22-30 px per frame), ``noise``
  (3-6 Hz per pixel), ``size`` (480x640).

Measured over the 30 Hz windows (per-pixel ground-truth magnitude): per train sequence the
median is 0.2-6.2 px and the maximum 0.4-12 px. Simulation time on one shared CPU core: a
train sequence 1-5 s (the fastest-moving one up to ~10 s under load), the whole test split
~20 s, the mini split ~2 s; a disk-cached sequence opens in milliseconds.

Caching: an in-process cache (by split and name; :func:`clear_cache` empties it), and an
on-disk cache of project h5 files under ``$EVFLOW_CACHE`` (default ``~/.cache/evflow``) in
``synthetic/<split>/<name>-v<simulator version>-<config hash>.h5``, written atomically by the
h5 writer and re-used when present. Set ``EVFLOW_CACHE=off`` (or pass ``disk_cache=False``) to
keep everything in memory. A disk-cached reader serves the stored flow maps (consecutive frame
times) and computes any other window's flow exactly from the scene geometry, like the
in-memory reader.
"""

from __future__ import annotations

import functools
import hashlib
import json
import os
import warnings
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from envs.cache import cache_root
from envs.readers.base import EventReader, FlowGT
from envs.readers.h5 import H5Reader
from envs.simulator import SIMULATOR_VERSION, Scene, SceneConfig, SimulatedSequence, simulate
from envs.simulator.randomize import (
    FACTOR_SETS,
    RANDOMIZED_VERSION,
    STRESS_FACTORS,
    FactorRanges,
    draw_scene,
    draw_size,
)

__all__ = [
    "SequenceSpec",
    "RandomizedSpec",
    "SyntheticH5Reader",
    "SPLITS",
    "list_splits",
    "list_sequences",
    "get_spec",
    "dr_train_specs",
    "cache_path",
    "load_sequence",
    "generate_split",
    "start_generation",
    "clear_cache",
    "cache_root",
]


@dataclass(frozen=True)
class SequenceSpec:
    """One sequence of a split.

    name: unique across splits. seed: scene seed. height, width: pixels. duration_s: seconds.
    max_flow_px: bound on any visible point's displacement per frame interval (px), i.e. a
    speed bound of max_flow_px * fps px/s. fps: frame rate (= ground-truth grid).
    contrast: the texture's log-intensity range, (low, high) (``SceneConfig.random``; None:
    its default). leaf_size: the range of its smallest leaf radius, pixels (likewise).
    """

    name: str
    seed: int
    height: int
    width: int
    duration_s: float
    max_flow_px: float
    fps: float = 30.0
    contrast: tuple[float, float] | None = None
    leaf_size: tuple[float, float] | None = None

    def config(self) -> SceneConfig:
        return SceneConfig.random(self.seed, self.height, self.width, speed_px_s=self.max_flow_px * self.fps,
                                  contrast=self.contrast, leaf_size=self.leaf_size)

    def simulate(self) -> SimulatedSequence:
        return simulate(self.config(), self.duration_s, fps=self.fps)

    def cache_key(self) -> str:
        """Hash of everything that determines the output (spec, config, simulator version); a
        spec without ``contrast`` or ``leaf_size`` hashes as before the fields existed."""
        spec = {k: v for k, v in asdict(self).items() if not (k in ("contrast", "leaf_size") and v is None)}
        blob = json.dumps([spec, self.config().to_dict(), SIMULATOR_VERSION], sort_keys=True)
        return hashlib.sha1(blob.encode()).hexdigest()[:10]


@dataclass(frozen=True)
class RandomizedSpec:
    """One domain-randomised sequence: its scene is drawn by
    :func:`envs.simulator.randomize.draw_scene` from the factor ranges named by ``factors``
    (a key of ``FACTOR_SETS``: "train", "transfer", "traffic" or a stress group). height, width: the drawn size (stored so a split
    lists its sizes without drawing the scenes)."""

    name: str
    seed: int
    height: int
    width: int
    duration_s: float
    factors: str = "train"
    fps: float = 30.0

    def __post_init__(self) -> None:
        if self.factors not in FACTOR_SETS:
            raise ValueError(f"RandomizedSpec.factors must be one of {tuple(FACTOR_SETS)}, got {self.factors!r}")

    def ranges(self) -> FactorRanges:
        return FACTOR_SETS[self.factors]

    def config(self) -> SceneConfig:
        return draw_scene(self.seed, self.ranges(), duration_s=self.duration_s, fps=self.fps)

    def simulate(self) -> SimulatedSequence:
        return simulate(self.config(), self.duration_s, fps=self.fps)

    def cache_key(self) -> str:
        """Hash of everything that determines the output (spec, config, simulator and
        randomisation versions)."""
        versions = [SIMULATOR_VERSION] + ([RANDOMIZED_VERSION] if RANDOMIZED_VERSION > 1 else [])  # files of version 1 predate it
        blob = json.dumps([asdict(self), self.config().to_dict(), *versions], sort_keys=True)
        return hashlib.sha1(blob.encode()).hexdigest()[:10]


DR_TRAIN = "synthetic-dr-train"
DR_TRAIN_DEFAULT_SIZE = 256
DR_TRAIN_SEED = 10_000_000  # sequence i has seed DR_TRAIN_SEED + i (i below 10^7)
STRESS_SEED = 20_000_000
STRESS_PER_GROUP = 3
DR_VAL = "synthetic-dr-val"
DR_VAL_SEED = 30_000_000  # the training distribution, seeds no training sequence has
DR_VAL_SIZE = 8
TRANSFER_TRAIN = "synthetic-transfer-train"
TRANSFER_TRAIN_SEED = 40_000_000
TRANSFER_VAL = "synthetic-transfer-val"
TRANSFER_VAL_SEED = 50_000_000
TRAFFIC = "synthetic-traffic"
SOFT_TRAIN = "synthetic-train-soft"
#: the log-intensity range of ``synthetic-train-soft``'s textures (synthetic-train: 2-3)
SOFT_CONTRAST = (0.3, 1.5)
SPARSE_TRAIN = "synthetic-train-sparse"
#: the range of ``synthetic-train-sparse``'s smallest leaf radius, pixels (synthetic-train: 1.5-3)
SPARSE_LEAVES = (6.0, 24.0)
WIDE_TRAIN = "synthetic-train-wide"
#: ``synthetic-train-wide``'s frame size: synthetic-train-sparse's scenes on 4x the area
WIDE_SIZE = 256
TRAFFIC_SEED = 60_000_000
TRAFFIC_SIZE = 4

#: the endless randomised series: split -> (seed of sequence 0, factor set); ``SPLIT:N`` is the
#: first N of the series
SERIES = {DR_TRAIN: (DR_TRAIN_SEED, "train"), TRANSFER_TRAIN: (TRANSFER_TRAIN_SEED, "transfer")}


def dr_train_specs(n: int) -> list[RandomizedSpec]:
    """The first n sequences of ``synthetic-dr-train`` (sequence i does not depend on n)."""
    return series_specs(DR_TRAIN, n)


def series_specs(split: str, n: int) -> list[RandomizedSpec]:
    """The first n sequences of the randomised series ``split`` (a key of :data:`SERIES`;
    sequence i does not depend on n)."""
    if not 0 < n < 10_000_000:
        raise ValueError(f"{split}: the number of sequences must be in 1..9999999, got {n}")
    return list(_series_specs(split, n))


@functools.lru_cache(maxsize=8)
def _series_specs(split: str, n: int) -> tuple[RandomizedSpec, ...]:
    seed0, factors = SERIES[split]
    return tuple(_randomized(f"{split}-{i:05d}", seed0 + i, factors, 1.0) for i in range(n))


def _randomized(name: str, seed: int, factors: str, duration_s: float) -> RandomizedSpec:
    return RandomizedSpec(name, seed, *draw_size(seed, FACTOR_SETS[factors]), duration_s, factors)


def _stress_specs() -> list[RandomizedSpec]:
    specs = []
    for g, group in enumerate(STRESS_FACTORS):
        for i in range(STRESS_PER_GROUP):
            seed = STRESS_SEED + 100 * g + i
            specs.append(RandomizedSpec(f"synthetic-stress-{group}-{i}", seed, *draw_size(seed, STRESS_FACTORS[group]), 1.0, group))
    return specs


def _spread(n: int, low: float, high: float, seed: int) -> list[float]:
    """n motion bounds spread geometrically over [low, high], in a fixed shuffled order."""
    values = np.geomspace(low, high, n)
    return [round(float(v), 3) for v in values[np.random.default_rng(seed).permutation(n)]]


def _build_splits() -> dict[str, list[SequenceSpec]]:
    train = [
        SequenceSpec(f"synthetic-train-{i:03d}", 1000 + i, 128, 128, 2.0, m)
        for i, m in enumerate(_spread(32, 0.5, 14.0, seed=1))
    ]
    test = [
        SequenceSpec(f"synthetic-test-128-{i:02d}", 2000 + i, 128, 128, 1.0, m)
        for i, m in enumerate(_spread(8, 0.5, 14.0, seed=2))
    ]
    test += [
        SequenceSpec(f"synthetic-test-256-{i:02d}", 2100 + i, 256, 256, 1.0, m)
        for i, m in enumerate((1.0, 4.0, 12.0))
    ]
    def twin(split: str, size: int = 128, **texture) -> list[SequenceSpec]:
        """synthetic-train's scenes and motions under another name, frame size or texture."""
        return [SequenceSpec(f"{split}-{i:03d}", spec.seed, size, size, 2.0, spec.max_flow_px, **texture)
                for i, spec in enumerate(train)]

    # weaker textures: the same speeds with fewer events
    soft = twin(SOFT_TRAIN, contrast=SOFT_CONTRAST)
    # larger leaves: fewer, longer edges, most of the frame silent
    sparse = twin(SPARSE_TRAIN, leaf_size=SPARSE_LEAVES)
    # the same on 256x256 frames: long edges far apart, for crops that need the context
    wide = twin(WIDE_TRAIN, WIDE_SIZE, leaf_size=SPARSE_LEAVES)
    mini = [SequenceSpec(f"synthetic-mini-{i}", 3000 + i, 64, 64, 1.0, m) for i, m in enumerate((1.0, 3.0, 8.0))]
    return {
        "synthetic-train": train,
        SOFT_TRAIN: soft,
        SPARSE_TRAIN: sparse,
        WIDE_TRAIN: wide,
        "synthetic-test": test,
        "synthetic-mini": mini,
        DR_TRAIN: dr_train_specs(DR_TRAIN_DEFAULT_SIZE),
        "synthetic-stress": _stress_specs(),
        DR_VAL: [_randomized(f"{DR_VAL}-{i}", DR_VAL_SEED + i, "train", 1.0) for i in range(DR_VAL_SIZE)],
        TRANSFER_TRAIN: series_specs(TRANSFER_TRAIN, DR_TRAIN_DEFAULT_SIZE),
        TRANSFER_VAL: [_randomized(f"{TRANSFER_VAL}-{i}", TRANSFER_VAL_SEED + i, "transfer", 1.0) for i in range(DR_VAL_SIZE)],
        TRAFFIC: [_randomized(f"{TRAFFIC}-{i}", TRAFFIC_SEED + i, "traffic", 1.5) for i in range(TRAFFIC_SIZE)],
    }


SPLITS: dict[str, list[SequenceSpec | RandomizedSpec]] = _build_splits()


def list_splits() -> list[str]:
    return list(SPLITS)


def _split_folder(split: str) -> str:
    """The cache folder of a split: ``synthetic-dr-train:N`` shares ``synthetic-dr-train``'s."""
    return split.split(":", 1)[0]


def list_sequences(split: str) -> list[SequenceSpec | RandomizedSpec]:
    """The specs of a split, in order; ``synthetic-dr-train:N`` gives that split's first N.
    Unknown split -> ValueError listing the known ones."""
    series, _, count = split.partition(":")
    if count and series in SERIES:
        if not count.isdigit():
            raise ValueError(f"{split!r}: the number after {series}: must be a positive integer")
        return series_specs(series, int(count))
    if split not in SPLITS:
        raise ValueError(f"unknown synthetic split {split!r}; known splits: {', '.join(SPLITS)} "
                         f"(and {' or '.join(f'{s}:N' for s in SERIES)} for N sequences)")
    return list(SPLITS[split])


def get_spec(split: str, index_or_name: int | str) -> SequenceSpec:
    """A split's sequence by position or by name."""
    specs = list_sequences(split)
    if isinstance(index_or_name, (int, np.integer)):
        if not -len(specs) <= index_or_name < len(specs):
            raise IndexError(f"{split} has {len(specs)} sequences, no index {index_or_name}")
        return specs[index_or_name]
    for spec in specs:
        if spec.name == index_or_name:
            return spec
    raise KeyError(f"{split} has no sequence named {index_or_name!r}; names: {specs[0].name} .. {specs[-1].name}")


class SyntheticH5Reader(H5Reader):
    """A disk-cached synthetic sequence: events and frames from the file; flow from the stored
    maps where one matches the window exactly, else computed exactly from the scene geometry."""

    def __init__(self, path: str | os.PathLike, config: SceneConfig) -> None:
        super().__init__(path)
        self.config = config
        self._scene: Scene | None = None

    def flow_between(self, t_start: int, t_end: int) -> FlowGT | None:
        stored = self.stored_flow(t_start, t_end)  # exact stored map; otherwise exact geometry
        if stored is not None:
            return stored
        if self._scene is None:
            self._scene = Scene(self.config)  # geometry only: the textures stay unbuilt
        return self._scene.flow(t_start * 1e-6, t_end * 1e-6), np.ones(self.sensor_size, bool)


def cache_path(split: str, spec: SequenceSpec | RandomizedSpec, root: Path) -> Path:
    """Where the disk cache keeps one sequence of a split (module docstring)."""
    return root / "synthetic" / _split_folder(split) / f"{spec.name}-v{SIMULATOR_VERSION}-{spec.cache_key()}.h5"


# in-process cache, by (split, name, disk cache on): a disk-cached sequence's file path and config (each call opens its own
# handle, so a caller may close its reader), or an in-memory reader (close() is a no-op there)
_MEMORY: dict[tuple[str, str, bool], tuple[Path, SceneConfig] | EventReader] = {}


def clear_cache() -> None:
    """Forget the in-process cache (the disk cache stays)."""
    _MEMORY.clear()


def load_sequence(split: str, index_or_name: int | str, *, disk_cache: bool = True) -> EventReader:
    """The reader of one split sequence, simulated on first use and cached (module docstring).

    Returns an :class:`~envs.readers.base.EventReader` with exact flow for any window, the frame
    times as ground-truth grid (30 Hz) and the frames: a :class:`SyntheticH5Reader` on its own
    file handle (close it when done) when the disk cache is on, else a shared in-memory
    :class:`~envs.readers.base.ArrayReader`.
    """
    spec = get_spec(split, index_or_name)
    root = cache_root() if disk_cache else None
    key = (_split_folder(split), spec.name, root is not None)
    cached = _MEMORY.get(key)
    if isinstance(cached, EventReader):
        return cached
    if cached is not None and cached[0].exists():
        return SyntheticH5Reader(*cached)
    if root is None:
        reader = spec.simulate().reader(spec.name)
        _MEMORY[key] = reader
        return reader
    config = spec.config()
    path = cache_path(split, spec, root)
    if path.exists():
        try:
            reader = SyntheticH5Reader(path, config)
            _MEMORY[key] = (path, config)
            return reader
        except (OSError, ValueError) as err:  # unreadable cache file: simulate again
            warnings.warn(f"ignoring unreadable cache file {path}: {err}", stacklevel=2)
    sequence = spec.simulate()
    try:
        sequence.to_h5(path, name=spec.name, provenance={"split": _split_folder(split), "spec": asdict(spec)})
    except OSError as err:
        warnings.warn(f"could not write the synthetic cache {path} ({err}); keeping {spec.name} in memory", stacklevel=2)
        reader = sequence.reader(spec.name)
        _MEMORY[key] = reader
        return reader
    _MEMORY[key] = (path, config)
    return SyntheticH5Reader(path, config)


def _generate_one(split: str, index: int, out: str | None, fmt: str, overwrite: bool) -> tuple[str, str | None, float]:
    """Simulate and write one sequence (a worker's job): (name, path written or None when it
    existed already, seconds of events simulated)."""
    from envs.simulator.export import output_path, write_sequence

    spec = get_spec(split, index)
    provenance = {"split": _split_folder(split), "spec": asdict(spec)}
    if out is None:
        root = cache_root()
        if root is None:
            raise ValueError("the disk cache is off (EVFLOW_CACHE=off): give an output folder")
        path = cache_path(split, spec, root)
        if path.exists() and not overwrite:
            return spec.name, None, 0.0
        spec.simulate().to_h5(path, name=spec.name, provenance=provenance)
        return spec.name, str(path), spec.duration_s
    stem = Path(out) / spec.name
    if output_path(stem, fmt).exists() and not overwrite:
        return spec.name, None, 0.0
    path = write_sequence(spec.simulate(), stem, fmt, name=spec.name, provenance=provenance)
    return spec.name, str(path), spec.duration_s


def generate_split(
    split: str,
    out: str | os.PathLike | None = None,
    *,
    fmt: str = "evflow-h5",
    num: int | None = None,
    workers: int = 1,
    overwrite: bool = False,
    progress: bool = True,
) -> list[Path]:
    """Simulate a split's sequences into files, in ``workers`` processes, with a progress bar.

    out: a folder for files named after the sequences, in ``fmt`` (envs.simulator.export);
        None fills the disk cache that :func:`load_sequence` reads (evflow-h5 only).
    num: only the first ``num`` sequences. Existing files are skipped unless ``overwrite``.
    Returns the paths written.
    """
    from concurrent.futures import ProcessPoolExecutor, as_completed

    from tqdm import tqdm

    from envs.simulator.export import OUTPUT_FORMATS

    if fmt not in OUTPUT_FORMATS:
        raise ValueError(f"fmt must be one of {OUTPUT_FORMATS}, got {fmt!r}")
    if out is None and fmt != "evflow-h5":
        raise ValueError(f"the disk cache holds evflow-h5 files; give an output folder for {fmt!r}")
    count = len(list_sequences(split)) if num is None else min(num, len(list_sequences(split)))
    jobs = [(split, i, None if out is None else str(out), fmt, overwrite) for i in range(count)]
    written: list[Path] = []
    bar = tqdm(total=count, desc=split, unit="seq", disable=not progress)
    if workers <= 1:
        for job in jobs:
            name, path, _ = _generate_one(*job)
            bar.set_postfix_str(name)
            written += [Path(path)] if path else []
            bar.update()
    else:
        with ProcessPoolExecutor(workers) as pool:
            for future in as_completed([pool.submit(_generate_one, *job) for job in jobs]):
                name, path, _ = future.result()
                bar.set_postfix_str(name)
                written += [Path(path)] if path else []
                bar.update()
    bar.close()
    return sorted(written)


def start_generation(split: str, *, num: int | None = None, workers: int = 1):
    """Fill the disk cache with a split's sequences in the background (:func:`generate_split`
    in a separate process, without a progress bar), so that training started meanwhile finds
    them cached. Returns the started ``multiprocessing.Process``: ``join()`` it to wait,
    ``terminate()`` it to stop (files are written atomically, so none is left half-written)."""
    import multiprocessing

    if cache_root() is None:
        raise ValueError("the disk cache is off (EVFLOW_CACHE=off): nothing to fill in the background")
    list_sequences(split)  # an unknown split fails here, not in the background
    process = multiprocessing.get_context("spawn").Process(
        target=generate_split, args=(split, None), kwargs={"num": num, "workers": workers, "progress": False}, name=f"generate {split}"
    )
    process.start()
    return process
