"""A Beta policy distribution on a box, for torchrl's ProbabilisticActor."""

from __future__ import annotations

import math

import torch
from torch import Tensor
from torch.distributions import Beta, Distribution, constraints

__all__ = ["ScaledBeta"]


class ScaledBeta(Distribution):
    """Independent Beta distributions mapped affinely from [0, 1] to [low, high] per dimension.

    ``x = low + (high - low) * u`` with ``u ~ Beta(concentration1, concentration0)`` in every
    action dimension. The last dim of the concentrations is the event (the action vector), so
    ``log_prob`` and ``entropy`` are joint over the action dims: with concentrations [B, K, 6]
    they return [B, K], one value per agent. ``deterministic_sample`` (what torchrl's
    ``ExplorationType.DETERMINISTIC`` uses for evaluation) and ``mean`` are the mean; ``mode`` is
    the true mode of the Beta, defined for concentrations above 1.

    Args:
        concentration1: Beta alpha, [..., A], positive.
        concentration0: Beta beta, [..., A], positive.
        low: lower end of the support.
        high: upper end of the support.
        eps: ``log_prob`` clamps values this far (in [0, 1] units) inside the open support, so
            actions exactly at ``low`` or ``high`` (possible in float32 sampling) stay finite.
        validate_args: passed to ``torch.distributions.Distribution``.

    Examples:
        >>> dist = ScaledBeta(torch.full((2, 8, 6), 2.0), torch.full((2, 8, 6), 2.0))
        >>> action = dist.sample()
        >>> action.shape, dist.log_prob(action).shape, dist.entropy().shape
        (torch.Size([2, 8, 6]), torch.Size([2, 8]), torch.Size([2, 8]))
        >>> bool(action.abs().le(1).all()), dist.deterministic_sample.abs().max()
        (True, tensor(0.))
    """

    arg_constraints = {
        "concentration1": constraints.positive,
        "concentration0": constraints.positive,
    }
    has_rsample = True

    def __init__(
        self,
        concentration1: Tensor,
        concentration0: Tensor,
        *,
        low: float = -1.0,
        high: float = 1.0,
        eps: float = 1e-6,
        validate_args: bool | None = None,
    ) -> None:
        if not high > low:
            raise ValueError(f"expected high > low, got low={low}, high={high}.")
        self.unit_beta = Beta(concentration1, concentration0, validate_args=validate_args)
        self.low = low
        self.high = high
        self.eps = eps
        shape = self.unit_beta.batch_shape
        super().__init__(shape[:-1], shape[-1:], validate_args=validate_args)

    @property
    def concentration1(self) -> Tensor:
        return self.unit_beta.concentration1

    @property
    def concentration0(self) -> Tensor:
        return self.unit_beta.concentration0

    @property
    def _scale(self) -> float:
        return self.high - self.low

    @constraints.dependent_property(is_discrete=False, event_dim=1)
    def support(self) -> constraints.Constraint:
        return constraints.independent(constraints.interval(self.low, self.high), 1)

    def _to_box(self, unit: Tensor) -> Tensor:
        return self.low + self._scale * unit

    @property
    def mean(self) -> Tensor:
        return self._to_box(self.unit_beta.mean)

    @property
    def mode(self) -> Tensor:
        return self._to_box(self.unit_beta.mode)

    @property
    def deterministic_sample(self) -> Tensor:
        return self.mean

    @property
    def variance(self) -> Tensor:
        return self.unit_beta.variance * self._scale**2

    def rsample(self, sample_shape: torch.Size | tuple[int, ...] = ()) -> Tensor:
        return self._to_box(self.unit_beta.rsample(sample_shape))

    def log_prob(self, value: Tensor) -> Tensor:
        """Joint log-density of actions [..., A] (summed over A; change of variables included)."""
        if self._validate_args:
            self._validate_sample(value)
        unit = ((value - self.low) / self._scale).clamp(self.eps, 1.0 - self.eps)
        log_density = self.unit_beta.log_prob(unit).sum(-1)
        return log_density - self.event_shape[0] * math.log(self._scale)

    def entropy(self) -> Tensor:
        """Joint differential entropy: sum over dims of the Beta entropy + log(high - low)."""
        return self.unit_beta.entropy().sum(-1) + self.event_shape[0] * math.log(self._scale)
