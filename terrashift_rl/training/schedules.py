"""Linear schedules of training hyper-parameters, indexed by update iteration."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class LinearSchedule:
    """Goes linearly from ``start`` to ``end`` over ``iterations`` updates, then stays at ``end``.

    Example:
        >>> schedule = LinearSchedule(0.2, 0.1, iterations=10)
        >>> schedule(0), schedule(5), schedule(10), schedule(50)
        (0.2, 0.15000000000000002, 0.1, 0.1)
    """

    start: float
    end: float
    iterations: int

    def __call__(self, iteration: int) -> float:
        if self.iterations <= 0:
            return self.end
        fraction = min(max(iteration / self.iterations, 0.0), 1.0)
        return self.start + fraction * (self.end - self.start)
