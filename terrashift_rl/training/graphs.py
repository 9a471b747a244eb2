"""Replaying a TensorDict function as a CUDA graph, so that its Python and kernel-launch cost is
paid once instead of at every call.

The trainer's two hot calls launch hundreds to thousands of kernels each: the actor's step
during collection and the mini-batch update (loss, backward, gradient clipping, AdamW). Replayed,
they cost GPU time only: at the default recipe's setting collection takes 30% less time, while
the update, GPU-bound at 8,192 env-steps per mini-batch, gains 3% (``docs/benchmarks.md``).
:class:`CudaGraphed` runs the first ``warmup`` calls eagerly on a side stream (real calls, whose
results count), captures the function on the next call's inputs, and from then on copies each
call's inputs into the captured ones and replays the graph.

A captured function must have a fixed input structure and shapes, no host synchronisation
(``.item()``, data-dependent Python branches, argument validation of distributions) and read
every changing setting from tensors that are updated in place (learning rates, loss
coefficients). Parameters and optimiser state must keep their storage: ``load_state_dict`` of a
module copies in place, an optimiser's does not (build a new :class:`CudaGraphed` after it).
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from tensordict import TensorDictBase

__all__ = ["CudaGraphed"]


class CudaGraphed:
    """``function(tensordict) -> tensordict`` replayed as a CUDA graph after ``warmup`` calls.

    Calls must all be on one CUDA device with the same keys, shapes and dtypes. The returned
    tensordict is the graph's output: the next call overwrites it, so clone what has to outlive
    that call.

    Args:
        function: maps a tensordict to a tensordict of tensors it produced.
        warmup: eager calls before the capture (lazy initialisation, e.g. of optimiser state,
            must happen outside the graph).

    Examples:
        >>> from tensordict import TensorDict
        >>> double = CudaGraphed(lambda td: TensorDict({"y": 2 * td["x"]}, td.batch_size))
        >>> x = TensorDict({"x": torch.ones(3)}, [3], device="cuda")  # doctest: +SKIP
        >>> [double(x)["y"].sum().item() for _ in range(4)]  # doctest: +SKIP
        [6.0, 6.0, 6.0, 6.0]
    """

    def __init__(
        self, function: Callable[[TensorDictBase], TensorDictBase], *, warmup: int = 2
    ) -> None:
        if warmup < 1:
            raise ValueError(f"warmup must be at least 1 eager call, got {warmup}")
        self.function = function
        self.warmup = warmup
        self.calls = 0
        self._graph: torch.cuda.CUDAGraph | None = None
        self._inputs: TensorDictBase | None = None
        self._outputs: TensorDictBase | None = None

    @property
    def captured(self) -> bool:
        """Whether the graph has been captured (calls now replay it)."""
        return self._graph is not None

    def __call__(self, tensordict: TensorDictBase) -> TensorDictBase:
        if tensordict.device is None or tensordict.device.type != "cuda":
            raise ValueError(
                f"CudaGraphed needs a tensordict on a CUDA device, got device {tensordict.device}"
            )
        self.calls += 1
        if self._graph is not None:
            self._inputs.update_(tensordict)
            self._graph.replay()
            return self._outputs
        if self.calls <= self.warmup:
            # eagerly, on a side stream as the capture will be: lazy state is created here
            current = torch.cuda.current_stream(tensordict.device)
            side = torch.cuda.Stream(tensordict.device)
            side.wait_stream(current)
            with torch.cuda.stream(side):
                outputs = self.function(tensordict)
            current.wait_stream(side)
            return outputs
        self._inputs = tensordict.clone()
        graph = torch.cuda.CUDAGraph()
        with torch.cuda.graph(graph):
            outputs = self.function(self._inputs)
        self._graph, self._outputs = graph, outputs  # only once the capture has succeeded
        graph.replay()  # the capture only recorded the call; this runs it
        return outputs
