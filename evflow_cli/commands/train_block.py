"""Train the learned finish (agents/update_block.py): a small update block that finishes the
shipped network's proposals in K iterations. The network is frozen; its proposals (the
default's: sensor pixels up to 3 frames, a 3x coarser grid beyond, docs/finish.md) are computed
once on the simulator's training split, then the block trains on them for a wall-clock budget.
Its target (--target): "loss", the solve's loss after the iterations (the env's reward with the
solve's stronger smoothness term), or "teacher", the --cmax solve from zero flow of each window.
Unsupervised either way: only events; no ground truth, no devval (choose on devval afterwards
with ``scripts/tradeoff.py --block OUT/block.pt``). Measured so far (docs/finish.md, "A learned
finish"): behind the default's 20-step solve on devval with either target, so not shipped.

  python scripts/train_block.py --minutes 40 --windows 30 --threads 1 --out runs/block
  python scripts/train_block.py --target teacher --dt 2 4 8 --minutes 25 --windows 30 --threads 1 --out runs/block-teacher
  python scripts/train_block.py --minutes 45 --out runs/block --resume        # goes on from runs/block/block.pt
"""

from __future__ import annotations

import dataclasses
import json
import random
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
import torch

from agents.checkpoint import save_checkpoint
from agents.options import (
    DeviceOptions,
    Progress,
    command_parser,
    non_negative_int,
    option,
    options_from_args,
    positive_int,
)
from agents.update_block import BLOCK_KIND, FLOW_SCALING, SPEC, UpdateBlock, frames_of, learned_finish, load_block
from envs.atomic import write_atomic
from losses import window_loss, zero_flow_loss


@dataclass(kw_only=True)
class TrainBlockOptions(DeviceOptions, Progress):
    """What scripts/train_block.py trains on, for how long, and where it writes."""

    data: str = "synthetic-train"
    """the simulator split the proposals are taken on (never devval)"""
    dt: list[int] = option(default_factory=lambda: [1, 2, 4, 8], type=positive_int)
    """window lengths in frames"""
    windows: int = option(12, type=positive_int)
    """windows per sequence and length (from each sequence's start)"""
    target: Literal["loss", "teacher"] = "loss"
    """what the block learns: "loss", to lower the solve's loss after its iterations; "teacher", to
    move the proposal onto the --cmax solve from zero flow (agents.cmax.CMaxSettings(), 100 steps,
    solved once per window and kept in OUT/teacher.npz): unsupervised either way (events only)"""
    iterations: int = option(4, type=positive_int)
    """the block's iterations per finish (K)"""
    gamma: float = 0.8
    """the loss after iteration k weighs gamma^(K - k) (the last weighs 1)"""
    max_events: int = option(16000, type=positive_int)
    """an even subsample of at most this many events per window (the finish's bound)"""
    batch: int = option(4, type=positive_int)
    """windows per update (their gradients summed)"""
    lr: float = 5e-4
    """Adam's step size"""
    hidden: int = option(32, type=positive_int)
    """the block's channels"""
    cells: int = option(16, type=non_negative_int)
    """the correction's grid: cells along the longer side (16: the solve's finest; 0: the block's own 4x coarser grid)"""
    minutes: float = 30.0
    """wall-clock budget of the training (the proposals' collection not counted)"""
    seed: int = 0
    """the order of the windows and the block's initial weights"""
    out: str = "runs/block"
    """output folder: block.pt (the block, its optimizer and its curve) and curve.json"""
    resume: bool = False
    """go on from OUT/block.pt"""


def _cache_key(options: TrainBlockOptions) -> str:
    from agents.pretrained import default_finish

    return json.dumps({"data": options.data, "dt": list(options.dt), "windows": options.windows,
                       "max_events": options.max_events, "finish": default_finish()}, sort_keys=True)


def save_pairs(path: Path, pairs: list[tuple], key: str) -> None:
    """The collected (window, proposal) pairs in one npz (atomically): events concatenated, one
    row of bounds per window, proposals flattened with their shapes."""
    import io

    rows = np.array([(len(w.events), w.t_start, w.t_end, *w.events.sensor_size, *p.shape[1:]) for w, p in pairs],
                    np.int64).reshape(-1, 7)
    buffer = io.BytesIO()
    np.savez(buffer, key=np.array(key), rows=rows,
             x=np.concatenate([w.events.x for w, _ in pairs]), y=np.concatenate([w.events.y for w, _ in pairs]),
             t=np.concatenate([w.events.t for w, _ in pairs]), p=np.concatenate([w.events.p for w, _ in pairs]),
             flows=np.concatenate([p.reshape(-1) for _, p in pairs]).astype(np.float32))
    write_atomic(path, buffer.getvalue())


def load_pairs(path: Path, key: str) -> list[tuple] | None:
    """The pairs :func:`save_pairs` wrote with the same ``key`` (None: no file, or another key)."""
    from envs.events import Events
    from envs.windows import Window

    if not path.exists():
        return None
    with np.load(path, allow_pickle=False) as data:
        if str(data["key"]) != key:
            return None
        rows, x, y, t, p, flows = (data[k] for k in ("rows", "x", "y", "t", "p", "flows"))
    pairs, at, flow_at = [], 0, 0
    for index, (n, t0, t1, height, width, fh, fw) in enumerate(rows.tolist()):
        events = Events(x[at:at + n], y[at:at + n], t[at:at + n], p[at:at + n], (height, width))
        pairs.append((Window(index, t0, t1, 0, n, events), flows[flow_at:flow_at + 2 * fh * fw].reshape(2, fh, fw)))
        at, flow_at = at + n, flow_at + 2 * fh * fw
    return pairs


def collect(options: TrainBlockOptions, echo=print) -> list[tuple]:
    """(window, proposal (2, H, W) float32) pairs: the default's proposal on every window of
    ``options.windows`` per sequence at each length, events subsampled to ``max_events``
    (kept in OUT/proposals.npz and taken from there when the same options ask again)."""
    cache = Path(options.out) / "proposals.npz"
    pairs = load_pairs(cache, _cache_key(options))
    if pairs is not None:
        echo(f"[train_block] {len(pairs)} windows from {cache}")
        return pairs
    from agents.evaluation import evaluate
    from agents.policy import RecurrentPolicy
    from agents.pretrained import default_finish
    from agents.wrappers.refine import FinishedPolicy

    pairs = []

    class Recorder:
        def __init__(self, inner) -> None:
            self.inner, self.input_key, self.voxel_bins = inner, inner.input_key, inner.voxel_bins

        def reset(self, mask=None) -> None:
            self.inner.reset(mask)

        def act(self, obs, window=None):
            flow = self.inner.act(obs, window)
            if len(window.events):
                pairs.append((window.subsample(options.max_events, rounding="floor"), np.asarray(flow, np.float32)))
            return flow

    network = RecurrentPolicy.from_pretrained(device=options.device)
    proposer = FinishedPolicy(network, [dataclasses.replace(f, steps=0) for f in FinishedPolicy(network, default_finish()).finishes])
    for dt in options.dt:
        before = len(pairs)
        evaluate(Recorder(proposer), options.data, window="frames", window_size=dt, max_windows=options.windows,
                 progress=not options.no_progress, measures=())
        echo(f"[train_block] dt = {dt}: {len(pairs) - before} windows")
    if pairs:
        save_pairs(cache, pairs, _cache_key(options))
    return pairs


def teacher_flows(pairs: list[tuple], options: TrainBlockOptions, echo=print) -> list[np.ndarray]:
    """The --cmax solve from zero flow of every collected window (on the events kept for it), kept
    in OUT/teacher.npz beside the proposals and taken from there when the same options ask again."""
    from agents.cmax import CMaxSettings

    cache = Path(options.out) / "teacher.npz"
    key = _cache_key(options) + " teacher " + json.dumps(dataclasses.asdict(CMaxSettings()), sort_keys=True)
    if cache.exists():
        with np.load(cache, allow_pickle=False) as data:
            if str(data["key"]) == key:
                flat, at, flows = data["flows"], 0, []
                for _, proposal in pairs:
                    flows.append(flat[at:at + proposal.size].reshape(proposal.shape))
                    at += proposal.size
                echo(f"[train_block] teacher flows from {cache}")
                return flows
    import io

    from tqdm import tqdm

    settings = CMaxSettings()
    flows = [settings.solve(window, proposal.shape[-2:], device=options.device)
             for window, proposal in tqdm(pairs, desc="teacher (--cmax)", disable=options.no_progress)]
    buffer = io.BytesIO()
    np.savez(buffer, key=np.array(key), flows=np.concatenate([f.reshape(-1) for f in flows]).astype(np.float32))
    write_atomic(cache, buffer.getvalue())
    return flows


def teacher_losses(block: UpdateBlock, window, proposal: np.ndarray, teacher: np.ndarray, options: TrainBlockOptions,
                   device) -> list:
    """The endpoint distance to the teacher's flow after each iteration, in pixels per frame (a
    graph to the block)."""
    batch = window.batch(device=device)
    flow = torch.as_tensor(proposal, device=device)[None]
    target = torch.as_tensor(teacher, device=device)[None]
    frames = frames_of(window.duration_us)
    flows = learned_finish(block, flow, batch, steps=options.iterations, frames=frames, return_all=True)
    return [(f - target).pow(2).sum(1).add(1e-9).sqrt().mean(dim=(1, 2)) / frames for f in flows]


def relative_losses(block: UpdateBlock, window, proposal: np.ndarray, options: TrainBlockOptions, device) -> list:
    """The window's loss (the solve's: agents.update_block.SPEC) after each iteration over the
    proposal's (a graph to the block)."""
    batch = window.batch(device=device)
    flow = torch.as_tensor(proposal, device=device)[None]
    scale, spec = FLOW_SCALING, SPEC
    zero = zero_flow_loss(flow, batch, spec, flow_scaling=scale).per_sample
    with torch.no_grad():
        start = window_loss(flow, batch, spec, flow_scaling=scale, zero_flow=zero).per_sample.clamp_min(1e-6)
    flows = learned_finish(block, flow, batch, steps=options.iterations, frames=frames_of(window.duration_us),
                           return_all=True)
    return [window_loss(f, batch, spec, flow_scaling=scale, zero_flow=zero).per_sample / start for f in flows]


def build_parser():
    return command_parser(TrainBlockOptions, __doc__)


def main(argv=None) -> int:
    args = options_from_args(TrainBlockOptions, build_parser().parse_args(argv))
    if args.threads:
        torch.set_num_threads(args.threads)
    if not 0 < args.gamma <= 1:
        raise ValueError(f"--gamma must be in (0, 1], got {args.gamma}")
    if "devval" in Path(args.data).resolve().parts or Path(args.data).stem == "devval":
        raise ValueError("--data: devval is for choosing, never for training")
    out = Path(args.out)
    path = out / "block.pt"
    if path.exists() and not args.resume:
        raise FileExistsError(f"{path} exists: --resume to go on from it, or another --out")
    torch.manual_seed(args.seed)
    block = UpdateBlock(hidden=args.hidden, cells=args.cells).to(args.device)
    optimizer = torch.optim.Adam(block.parameters(), lr=args.lr)
    curve, updates, seconds = [], 0, 0.0
    if args.resume:
        block, payload = load_block(path, device=args.device)
        block.train()
        optimizer = torch.optim.Adam(block.parameters(), lr=args.lr)
        optimizer.load_state_dict(payload["optimizer"])
        curve, updates, seconds = payload["curve"], int(payload["updates"]), float(payload["seconds"])
    pairs = collect(args)
    if not pairs:
        raise ValueError(f"--data {args.data}: no window with events")
    teachers = teacher_flows(pairs, args) if args.target == "teacher" else None
    rng = random.Random(args.seed + updates)
    order: list[int] = []
    weights = [args.gamma ** (args.iterations - 1 - k) for k in range(args.iterations)]
    start, last_save, window_losses = time.monotonic(), time.monotonic(), []
    budget = args.minutes * 60.0
    print(f"[train_block] {len(pairs)} windows, block of {sum(p.numel() for p in block.parameters())} parameters, "
          f"{args.iterations} iterations, {args.minutes:g} min")
    while time.monotonic() - start < budget:
        optimizer.zero_grad(set_to_none=True)
        finals = []
        for _ in range(args.batch):
            if not order:
                order = list(range(len(pairs)))
                rng.shuffle(order)
            index = order.pop()
            window, proposal = pairs[index]
            if teachers is None:
                losses = relative_losses(block, window, proposal, args, args.device)
            else:
                losses = teacher_losses(block, window, proposal, teachers[index], args, args.device)
            total = sum(w * loss.sum() for w, loss in zip(weights, losses)) / (sum(weights) * args.batch)
            total.backward()
            finals.append(float(losses[-1].detach().sum()))
        torch.nn.utils.clip_grad_norm_(block.parameters(), 1.0)
        optimizer.step()
        updates += 1
        window_losses += finals
        if len(window_losses) >= 200 or time.monotonic() - start >= budget:
            elapsed = seconds + time.monotonic() - start
            curve.append({"update": updates, "seconds": round(elapsed, 1),
                          "loss": round(float(np.mean(window_losses)), 5)})
            what = ("loss after the finish over the proposal's" if teachers is None else
                    "distance to the teacher after the finish, px per frame")
            print(f"[train_block] update {updates} ({elapsed / 60:.1f} min): {what} "
                  f"{curve[-1]['loss']:.4f} (mean of {len(window_losses)} windows)",
                  flush=True)
            window_losses = []
        if time.monotonic() - last_save > 300:
            _save(path, block, optimizer, curve, updates, seconds + time.monotonic() - start, args)
            last_save = time.monotonic()
    _save(path, block, optimizer, curve, updates, seconds + time.monotonic() - start, args)
    write_atomic(out / "curve.json", json.dumps(curve, indent=1) + "\n")
    print(f"[train_block] wrote {path} ({updates} updates)")
    return 0


def _save(path: Path, block, optimizer, curve, updates: int, seconds: float, args) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    recipe = {k: v for k, v in dataclasses.asdict(args).items() if k not in ("no_progress",)}
    save_checkpoint(path, {"kind": BLOCK_KIND, "block": block.state_dict(), "block_config": block.config(),
                           "iterations": args.iterations, "optimizer": optimizer.state_dict(), "curve": curve,
                           "updates": updates, "seconds": seconds, "recipe": json.dumps(recipe)})


if __name__ == "__main__":
    raise SystemExit(main())
