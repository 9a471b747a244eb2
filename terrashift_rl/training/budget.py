"""How long a run trains: iterations until its env-step budget or its deadline, and the
env-steps at which that will stop (for a progress bar's total)."""

from __future__ import annotations

import math
import time
from collections.abc import Iterator

from terrashift_rl.training import distributed
from terrashift_rl.training.trainer import OnPolicyTrainer


def iterate_until(
    trainer: OnPolicyTrainer, *, total_env_steps: int, deadline: float | None
) -> Iterator[dict[str, float]]:
    """Runs iterations until ``total_env_steps`` or the wall-clock ``deadline``
    (``time.monotonic()`` value) is reached, yielding each iteration's metrics."""
    while trainer.env_steps < total_env_steps:
        if deadline is not None and distributed.any_process(time.monotonic() >= deadline):
            return
        yield trainer.train_iteration()


def planned_env_steps(
    env_steps: int,
    per_iteration: int,
    total_env_steps: int,
    *,
    seconds_left: float | None = None,
    seconds_per_iteration: float | None = None,
) -> int:
    """The env-steps at which :func:`iterate_until` will stop, from ``env_steps`` done and
    ``per_iteration`` per iteration: the first iteration's end at or past ``total_env_steps``,
    or earlier the last iteration that starts within ``seconds_left`` (the deadline) at
    ``seconds_per_iteration``.

    Example:
        >>> planned_env_steps(0, 1024, 100_000)  # 98 iterations
        100352
        >>> planned_env_steps(2048, 1024, 100_000, seconds_left=45.0, seconds_per_iteration=10.0)
        7168
    """
    iterations = math.ceil(max(total_env_steps - env_steps, 0) / per_iteration)
    if seconds_left is not None and seconds_per_iteration:
        iterations = min(iterations, math.ceil(max(seconds_left, 0.0) / seconds_per_iteration))
    return env_steps + iterations * per_iteration
