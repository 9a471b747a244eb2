"""Linear schedules of training hyper-parameters, indexed by update iteration."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from terrashift_rl.training.settings import TrainConfig


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


def training_schedules(config: TrainConfig) -> dict[str, LinearSchedule]:
    """The schedules of ``config`` over its ``schedule_iterations``: ``lr_factor`` (on both
    learning rates), the loss's ``clip_epsilon``, ``entropy_coeff`` and ``clip_value``, and
    ``max_grad_norm``."""
    n, loss = config.schedule_iterations, config.loss
    return {
        "lr_factor": LinearSchedule(1.0, config.lr_end_factor, n),
        "clip_epsilon": LinearSchedule(loss.clip_epsilon_start, loss.clip_epsilon_end, n),
        "entropy_coeff": LinearSchedule(loss.entropy_coeff_start, loss.entropy_coeff_end, n),
        "clip_value": LinearSchedule(loss.clip_value_start, loss.clip_value_end, n),
        "max_grad_norm": LinearSchedule(config.max_grad_norm_start, config.max_grad_norm_end, n),
    }
