"""Data-parallel training over the processes that ``torchrun`` starts, with torch.distributed.

Every process (a *rank*) builds its own ``train.num_envs`` environments on its own device
(``cuda:LOCAL_RANK`` with NCCL, or the CPU with gloo) with its own seed, collects its own batch
and takes the same optimiser steps as every other rank, on gradients averaged over all of them;
the global batch is ``world_size`` times a single process's. What the ranks exchange:

- once, when the trainer is built: rank 0's parameters and buffers (:func:`broadcast_from_main`);
- at every mini-batch: the gradients, in one flat all-reduce between backward and clipping
  (:func:`average_gradients`), and with ``lr_schedule=adaptive`` the KL estimate the learning
  rate follows (:func:`average`); both are captured in the update's CUDA graph;
- at every value-estimation pass: the moments of the new returns, so the return statistics stay
  one (:class:`~terrashift_rl.objectives.normalization.ValueNormalizer` with ``synchronize``);
- at every iteration: the mean loss terms (so that every rank reaches the same verdict on
  non-finite values), the metrics rank 0 logs (:func:`combine_metrics`) and whether to stop
  (:func:`any_process`);
- at every checkpoint: each rank's environments and random streams, gathered to rank 0
  (:func:`gather_to_main`), which alone writes files.

With no process group (a plain ``python`` run) every function here is the identity or does
nothing, so a single process trains exactly as it would without them.
"""

from __future__ import annotations

import io
import os
from collections.abc import Iterable, Sequence
from typing import Any

import torch
import torch.distributed as dist
from torch import Tensor, nn

__all__ = [
    "any_process",
    "average",
    "average_gradients",
    "broadcast_from_main",
    "combine_metrics",
    "destroy_process_group",
    "gather_to_main",
    "init_process_group",
    "is_distributed",
    "is_main_process",
    "launched",
    "rank",
    "rank_entries",
    "world_size",
]

BACKENDS = {"cuda": "nccl", "cpu": "gloo"}
"""The torch.distributed backend of each kind of device."""


def launched() -> bool:
    """Whether a launcher (``torchrun``) started this process as one rank of a group: it sets
    ``WORLD_SIZE``, with ``RANK``, ``LOCAL_RANK``, ``MASTER_ADDR`` and ``MASTER_PORT``."""
    return "WORLD_SIZE" in os.environ


def init_process_group(device: Any, *, key: str) -> torch.device:
    """Joins the process group that torchrun's environment variables describe and returns this
    process's device, for the device setting ``key`` = ``device``: ``cuda`` (or ``auto`` where
    CUDA is present) gives ``cuda:LOCAL_RANK`` and NCCL, ``cpu`` (or ``auto`` without CUDA) the
    CPU and gloo.

    Raises ``ValueError`` naming ``key`` for another value (``cuda:<index>``: each rank takes its
    local rank's GPU) and when torchrun started more processes on this host than it has GPUs.
    """
    if device == "auto":
        kind = "cuda" if torch.cuda.is_available() else "cpu"
    elif device in BACKENDS:
        kind = device
    else:
        raise ValueError(
            f"{key}={device!r}, but under torchrun {key} must be auto, cuda or cpu: each process "
            "takes the GPU of its local rank (cuda:LOCAL_RANK)"
        )
    if kind == "cuda":
        processes = int(os.environ.get("LOCAL_WORLD_SIZE", os.environ["WORLD_SIZE"]))
        gpus = torch.cuda.device_count()
        if processes > gpus:
            raise ValueError(
                f"torchrun started {processes} processes on this host, which has {gpus} CUDA "
                f"device(s): one process per GPU, so use --nproc_per_node={gpus} or fewer (or "
                f"{key}=cpu)"
            )
        local = torch.device("cuda", int(os.environ.get("LOCAL_RANK", "0")))
        torch.cuda.set_device(local)
    else:
        local = torch.device("cpu")
    if not is_distributed():
        dist.init_process_group(BACKENDS[kind], device_id=local if kind == "cuda" else None)
    return local


def destroy_process_group() -> None:
    """Leaves the process group, if this process is in one."""
    if is_distributed():
        dist.destroy_process_group()


def is_distributed() -> bool:
    """Whether this process is in a torch.distributed process group."""
    return dist.is_available() and dist.is_initialized()


def world_size() -> int:
    """The number of processes training together: 1 without a process group."""
    return dist.get_world_size() if is_distributed() else 1


def rank() -> int:
    """This process's rank: 0 without a process group."""
    return dist.get_rank() if is_distributed() else 0


def is_main_process() -> bool:
    """Whether this process is rank 0, the one that logs and writes files; before it joins its
    group, the ``RANK`` that torchrun set says (a plain run is rank 0)."""
    if is_distributed():
        return dist.get_rank() == 0
    return int(os.environ.get("RANK", "0")) == 0


def average(tensor: Tensor) -> Tensor:
    """The mean of ``tensor`` over the processes, as a new tensor (``tensor`` itself in a single
    process). Every process must call it, with a tensor of the same shape."""
    if world_size() == 1:
        return tensor
    total = tensor.detach().clone()
    dist.all_reduce(total)
    return total.div_(dist.get_world_size())


def average_gradients(parameters: Sequence[nn.Parameter]) -> None:
    """Replaces the gradients of ``parameters`` by their means over the processes, in a single
    all-reduce of one flat buffer (one collective per update, and no host synchronisation, so a
    CUDA graph can capture it). Every process must pass the same parameters, each with a
    gradient; afterwards the gradients are views of that buffer."""
    if world_size() == 1 or not parameters:
        return
    flat = torch.cat([parameter.grad.reshape(-1) for parameter in parameters])
    dist.all_reduce(flat)
    flat.div_(dist.get_world_size())
    pieces = flat.split([parameter.numel() for parameter in parameters])
    for parameter, piece in zip(parameters, pieces, strict=True):
        parameter.grad = piece.view_as(parameter)


def broadcast_from_main(modules: Iterable[nn.Module]) -> None:
    """Copies rank 0's parameters and buffers of ``modules`` into every other rank's, so that
    training starts from one set of weights whatever each rank's seed."""
    if world_size() == 1:
        return
    tensors = {id(t): t for module in modules for t in (*module.parameters(), *module.buffers())}
    with torch.no_grad():
        for tensor in tensors.values():
            dist.broadcast(tensor.data, src=0)


def any_process(flag: bool) -> bool:
    """Whether ``flag`` is true on any process: a decision every rank then takes alike, such as
    stopping, however its own signal or clock fell (``flag`` itself in a single process)."""
    if world_size() == 1:
        return flag
    nccl = dist.get_backend() == "nccl"  # which only reduces tensors on a GPU
    device = torch.device("cuda", torch.cuda.current_device()) if nccl else torch.device("cpu")
    value = torch.tensor(float(flag), device=device)
    dist.all_reduce(value, op=dist.ReduceOp.MAX)
    return bool(value.item())


def gather_to_main(value: Any) -> list[Any] | None:
    """Every process's ``value`` (what ``torch.save`` writes; tensors on the CPU), in rank
    order, on rank 0; ``None`` on the others. In a single process, ``[value]``."""
    if world_size() == 1:
        return [value]
    # through torch.save: pickle alone refuses tensors of some dtypes (uint32 random streams)
    buffer = io.BytesIO()
    torch.save(value, buffer)
    gathered = [None] * dist.get_world_size() if dist.get_rank() == 0 else None
    dist.gather_object(buffer.getvalue(), gathered, dst=0)
    if gathered is None:
        return None
    # written by this run's own processes a moment ago: nothing foreign is unpickled
    return [torch.load(io.BytesIO(data), weights_only=False) for data in gathered]


def combine_metrics(metrics: dict[str, float], *, summed: Iterable[str]) -> dict[str, float]:
    """One iteration's metrics over every process: the names in ``summed`` added up (counts and
    rates of the whole group), every other one averaged over the processes that report it
    (a metric that every process reports alike keeps its value). ``metrics`` in a single
    process."""
    if world_size() == 1:
        return metrics
    gathered: list[dict[str, float]] = [{}] * dist.get_world_size()
    dist.all_gather_object(gathered, metrics)
    summed = set(summed)
    combined = {}
    for name in dict.fromkeys(name for values in gathered for name in values):
        values = [reported[name] for reported in gathered if name in reported]
        if name in summed:
            combined[name] = sum(values)
        elif values.count(values[0]) == len(values):
            combined[name] = values[0]
        else:
            combined[name] = sum(values) / len(values)
    return combined


def rank_entries(state: dict[str, Any], keys: Sequence[str]) -> dict[str, Any] | None:
    """This rank's ``keys`` in a checkpoint: rank 0's are the checkpoint's own entries, those of
    rank r > 0 its ``rank_states[r - 1]``; ``None`` for a rank the checkpoint's run did not have
    (it was trained by fewer processes)."""
    own = rank()
    if own == 0:
        return {key: state[key] for key in keys}
    others = state.get("rank_states") or []
    return others[own - 1] if own - 1 < len(others) else None
