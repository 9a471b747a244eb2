"""Data-parallel training over the processes that ``torchrun`` starts, with torch.distributed.

Every process (a *rank*) builds its own ``train.num_envs`` environments on its own device
(``cuda:LOCAL_RANK`` with NCCL, or the CPU with gloo) with its own seed, collects its own batch
and takes the same optimiser steps as every other rank, on gradients averaged over all of them;
the global batch is ``world_size`` times a single process's. Each rank splits its batch into
``world_size`` times ``train.minibatches`` mini-batches, so that an optimiser step averages as
many sequences, and a run takes as many steps per env-step, as a single process. What the ranks
exchange:

- once, when the trainer is built: rank 0's parameters and buffers (:func:`broadcast_from_main`);
- at every mini-batch: the gradients (with ``lr_schedule=adaptive`` also the KL estimate the
  learning rate follows), in one flat all-reduce (:func:`average`) between the backward pass
  and the optimiser step. With CUDA graphs the trainer replays the backward pass and the step as
  two graphs and runs the all-reduce between them, eagerly: no collective is ever captured;
- at every value-estimation pass: the moments of the new returns, so the return statistics stay
  one (:class:`~terrashift_rl.objectives.normalization.ValueNormalizer` with ``synchronize``);
- at every iteration: the mean loss terms (so that every rank reaches the same verdict on
  non-finite values), the metrics rank 0 logs (:func:`combine_metrics`) and whether to stop
  (:func:`any_process`);
- at every checkpoint: each rank's environments and random streams, gathered to rank 0
  (:func:`gather_to_main`), which alone writes files.

No exchange waits forever. Every collective runs under the process group's timeout (with NCCL,
torch's watchdog aborts a collective that exceeds it), and each stretch of work that ends by
waiting for the other ranks runs under :func:`watch`: when one lasts longer than the timeout, a
thread of this process writes which rank, iteration and exchange it was, with every thread's
stack, and ends the process; ``torchrun`` then stops the other ranks.

With no process group (a plain ``python`` run) every function here is the identity or does
nothing, so a single process trains exactly as it would without them.
"""

from __future__ import annotations

import contextlib
import faulthandler
import io
import os
import sys
import threading
import time
from collections.abc import Iterable, Iterator, Sequence
from datetime import timedelta
from typing import Any

import torch
import torch.distributed as dist
from torch import Tensor, nn

__all__ = [
    "Watchdog",
    "any_process",
    "average",
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
    "watch",
    "world_size",
    "world_size_change",
]

BACKENDS = {"cuda": "nccl", "cpu": "gloo"}
"""The torch.distributed backend of each kind of device."""

WATCHDOG_EXIT_CODE = 75
"""The exit status of a rank that the :class:`Watchdog` ended."""
BACKSTOP_S = 30.0
"""How much longer than the watchdog's timeout the process group's own timeout is: torch's
watchdog (NCCL) or a collective's error (gloo) ends a rank only where this module's has not."""


def launched() -> bool:
    """Whether a launcher (``torchrun``) started this process as one rank of a group: it sets
    ``WORLD_SIZE``, with ``RANK``, ``LOCAL_RANK``, ``MASTER_ADDR`` and ``MASTER_PORT``."""
    return "WORLD_SIZE" in os.environ


def init_process_group(
    device: Any, *, key: str, timeout: float = 300.0, timeout_key: str = "timeout"
) -> torch.device:
    """Joins the process group that torchrun's environment variables describe and returns this
    process's device, for the device setting ``key`` = ``device``: ``cuda`` (or ``auto`` where
    CUDA is present) gives ``cuda:LOCAL_RANK`` and NCCL, ``cpu`` (or ``auto`` without CUDA) the
    CPU and gloo.

    A stretch of waiting for the other ranks (:func:`watch`) then lasts at most ``timeout``
    seconds (the setting ``timeout_key``, named in the message) before a :class:`Watchdog` ends
    this process; every collective also runs under the process group's timeout,
    :data:`BACKSTOP_S` longer, which torch enforces (for NCCL with its watchdog thread and
    asynchronous error handling).

    Raises ``ValueError`` naming ``key`` for another value (``cuda:<index>``: each rank takes its
    local rank's GPU) and when torchrun started more processes on this host than it has GPUs.
    """
    global _watchdog
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
        # a collective past the timeout aborts the process instead of blocking (torch's default
        # too; set here so that an inherited 0 cannot turn it off unseen)
        os.environ["TORCH_NCCL_ASYNC_ERROR_HANDLING"] = "3"
        dist.init_process_group(
            BACKENDS[kind],
            device_id=local if kind == "cuda" else None,
            timeout=timedelta(seconds=timeout + BACKSTOP_S),
        )
        _watchdog = Watchdog(timeout, rank=dist.get_rank(), setting=timeout_key)
    return local


def destroy_process_group() -> None:
    """Leaves the process group, if this process is in one, and stops its watchdog."""
    global _watchdog
    if is_distributed():
        dist.destroy_process_group()
    if _watchdog is not None:
        _watchdog.stop()
        _watchdog = None


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


class Watchdog:
    """Ends this process when a stretch of work that waits for the other ranks (:meth:`watch`)
    lasts longer than ``timeout`` seconds: a rank that stopped answering or died then takes the
    run down with a message, instead of leaving the others blocked.

    A thread checks the stretch in progress a few times per ``timeout``. When one has run out,
    it writes to standard error the rank, the iteration, the operation, how long it waited and
    the setting ``setting`` that holds the timeout, then every thread's Python stack
    (:mod:`faulthandler`), and ends the process with status :data:`WATCHDOG_EXIT_CODE`
    (``os._exit``: the main thread is blocked, and files are written atomically, so the last
    checkpoint stays whole). ``torchrun`` then stops the other ranks.

    Args:
        timeout: seconds a stretch may last.
        rank: this process's rank, for the message.
        setting: the name of the setting that holds ``timeout``, for the message.
    """

    def __init__(self, timeout: float, *, rank: int, setting: str = "timeout") -> None:
        if not timeout > 0:
            raise ValueError(f"{setting} must be a number of seconds > 0, got {timeout!r}")
        self.timeout = float(timeout)
        self.rank = rank
        self.setting = setting
        self.iteration: int | None = None
        """The iteration the last :meth:`watch` that named one was in."""
        self._waiting: tuple[str, float] | None = None  # (operation, since when)
        self._stopped = threading.Event()
        self._thread = threading.Thread(target=self._run, name="collective-watchdog", daemon=True)
        self._thread.start()

    @contextlib.contextmanager
    def watch(self, operation: str, *, iteration: int | None = None) -> Iterator[None]:
        """Marks the body as a stretch that waits for the other ranks in ``operation``."""
        if iteration is not None:
            self.iteration = iteration
        outer = self._waiting
        self._waiting = (operation, time.monotonic())
        try:
            yield
        finally:
            self._waiting = outer

    def stop(self) -> None:
        """Stops the checking thread."""
        self._stopped.set()
        self._thread.join()

    def _run(self) -> None:
        while not self._stopped.wait(min(1.0, self.timeout / 4)):
            waiting = self._waiting
            if waiting is not None and time.monotonic() - waiting[1] > self.timeout:
                self._abort(*waiting)

    def _abort(self, operation: str, since: float) -> None:
        iteration = "" if self.iteration is None else f" in iteration {self.iteration}"
        sys.stderr.write(
            f"rank {self.rank}: {operation}{iteration} has waited "
            f"{time.monotonic() - since:.0f} s for the other ranks, longer than "
            f"{self.setting}={self.timeout:g}: another rank stopped answering or died. Ending "
            f"this rank (exit status {WATCHDOG_EXIT_CODE}); torchrun stops the others. The "
            "last checkpoint written is whole. This rank's threads:\n"
        )
        sys.stderr.flush()
        faulthandler.dump_traceback(file=sys.stderr, all_threads=True)
        os._exit(WATCHDOG_EXIT_CODE)


_watchdog: Watchdog | None = None


def watch(operation: str, *, iteration: int | None = None) -> contextlib.AbstractContextManager:
    """:meth:`Watchdog.watch` of this process's watchdog; without a process group, nothing."""
    if _watchdog is None:
        return contextlib.nullcontext()
    return _watchdog.watch(operation, iteration=iteration)


def average(tensor: Tensor) -> Tensor:
    """The mean of ``tensor`` over the processes, as a new tensor (``tensor`` itself in a single
    process). Every process must call it, with a tensor of the same shape."""
    if world_size() == 1:
        return tensor
    total = tensor.detach().clone()
    dist.all_reduce(total)
    return total.div_(dist.get_world_size())


def broadcast_from_main(modules: Iterable[nn.Module]) -> None:
    """Copies rank 0's parameters and buffers of ``modules`` into every other rank's, so that
    training starts from one set of weights whatever each rank's seed."""
    if world_size() == 1:
        return
    tensors = {id(t): t for module in modules for t in (*module.parameters(), *module.buffers())}
    with torch.no_grad(), watch("the broadcast of rank 0's weights"):
        for tensor in tensors.values():
            dist.broadcast(tensor.data, src=0)
        dist.barrier()


def any_process(flag: bool, decision: str = "stopping") -> bool:
    """Whether ``flag`` is true on any process: a ``decision`` every rank then takes alike, such
    as stopping, however its own signal or clock fell (``flag`` itself in a single process)."""
    if world_size() == 1:
        return flag
    nccl = dist.get_backend() == "nccl"  # which only reduces tensors on a GPU
    device = torch.device("cuda", torch.cuda.current_device()) if nccl else torch.device("cpu")
    value = torch.tensor(float(flag), device=device)
    with watch(f"the vote on {decision}"):
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
    with watch("gathering the checkpoint's per-rank state"):
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
    with watch("the exchange of the metrics"):
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


def world_size_change(saved: int, now: int) -> str:
    """What resuming a checkpoint of ``saved`` processes with ``now`` processes does.

    Example:
        >>> world_size_change(4, 2).split("over, ")[1]
        'the environments of ranks 0-1 continue, those of ranks 2-3 are left behind'
        >>> world_size_change(1, 2).split("over, ")[1]
        'the environments of rank 0 continue, and new ones from run.seed + rank for rank 1'
    """

    def ranks(first: int, last: int) -> str:
        return f"rank {first}" if first == last else f"ranks {first}-{last}"

    change = (
        f"and new ones from run.seed + rank for {ranks(saved, now - 1)}"
        if now > saved
        else f"those of {ranks(now, saved - 1)} are left behind"
    )
    return (
        f"the checkpoint was trained by {saved} process(es) and continues with {now}: the "
        "weights, optimiser, return statistics and counters carry over, the environments of "
        f"{ranks(0, min(saved, now) - 1)} continue, {change}"
    )
