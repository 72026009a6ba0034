"""What the processes of a ``torchrun`` job exchange: averaged gradients, episode states, sums.

Gradients are averaged after the update's one backward with an all-reduce per bucket of about
25 MB of flattened gradients (DistributedDataParallel's default bucket size), all buckets started
together and awaited together, instead of one collective per parameter. The averaging is done
here rather than by wrapping the network in ``DistributedDataParallel``: the recurrent policy
runs the network L times through its stateful wrapper before that backward, and averaging after
it keeps DDP's per-forward bookkeeping out of the rollout; the sums are the same on gloo (CPU)
and NCCL (GPU). A model this size is not communication-bound, so the overlap with the backward
that DDP would add is not missed.

Every function here is a collective: all ranks call it, in the same order.
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

import torch
import torch.distributed as dist

__all__ = ["BUCKET_BYTES", "average_gradients", "gather_to_first", "all_reduce_sums"]

#: bytes of gradients per all-reduce (DistributedDataParallel's default bucket_cap_mb = 25)
BUCKET_BYTES = 25 * 2**20


def _buckets(tensors: list[torch.Tensor], bucket_bytes: int) -> list[list[torch.Tensor]]:
    """Consecutive tensors of one dtype and device, at most ``bucket_bytes`` per group (a larger
    tensor alone)."""
    buckets: list[list[torch.Tensor]] = []
    size = 0
    for tensor in tensors:
        nbytes = tensor.numel() * tensor.element_size()
        last = buckets[-1] if buckets else None
        if last is None or last[0].dtype != tensor.dtype or last[0].device != tensor.device or size + nbytes > bucket_bytes:
            buckets.append([tensor])
            size = nbytes
        else:
            last.append(tensor)
            size += nbytes
    return buckets


def average_gradients(parameters: Iterable[torch.nn.Parameter], world_size: int,
                      bucket_bytes: int = BUCKET_BYTES) -> None:
    """Replace every parameter's gradient by its mean over the ``world_size`` ranks, in place.
    A parameter without a gradient (unused in this update) takes part with zeros, so every rank
    sends the same buckets."""
    grads = []
    for parameter in parameters:
        if not parameter.requires_grad:
            continue
        if parameter.grad is None:
            parameter.grad = torch.zeros_like(parameter)
        grads.append(parameter.grad)
    buckets = _buckets(grads, bucket_bytes)
    flats = [torch.cat([grad.reshape(-1) for grad in bucket]) for bucket in buckets]
    works = [dist.all_reduce(flat, async_op=True) for flat in flats]
    for work, flat, bucket in zip(works, flats, buckets):
        work.wait()
        flat.div_(world_size)
        offset = 0
        for grad in bucket:  # copy_ keeps each gradient's own layout (channels-last or not)
            grad.copy_(flat[offset:offset + grad.numel()].view(grad.shape))
            offset += grad.numel()


def gather_to_first(value: Any) -> list[Any] | None:
    """Every rank's ``value`` (any picklable object; tensors on CPU) as a list indexed by rank on
    rank 0, None on the other ranks. Under NCCL the current CUDA device must be this rank's
    (``torch.cuda.set_device``)."""
    gathered = [None] * dist.get_world_size() if dist.get_rank() == 0 else None
    dist.gather_object(value, gathered, dst=0)
    return gathered


def all_reduce_sums(values: list[float], device: torch.device) -> list[float]:
    """The element-wise sums of ``values`` over the ranks (float64, on ``device``: a CUDA device
    under NCCL)."""
    total = torch.tensor(values, dtype=torch.float64, device=device)
    dist.all_reduce(total)
    return total.tolist()
