"""Running normalisation of value targets, so the critics learn returns of any scale in unit
variance."""

from __future__ import annotations

import torch
import torch.distributed as dist
from torch import Tensor, nn


class ValueNormalizer(nn.Module):
    """Running mean and standard deviation of value targets.

    The critics of a loss that holds one predict targets in normalised units: the value
    estimator maps their outputs back with :meth:`denormalize` before computing returns and
    advantages, then calls :meth:`update` with the new targets, and the regression losses
    compare outputs with :meth:`normalize` d targets. The statistics are exponential moving
    averages over calls to :meth:`update`, debiased as Adam's moments are, so the first batches
    are not pulled towards zero. Before the first update both maps are the identity. Outputs are
    not rescaled when the statistics move (no PopArt correction): with a decay near 1 they move
    slowly compared with the critics' learning.

    The statistics are buffers: they follow the module's device and its ``state_dict``.

    Args:
        decay: weight of the old statistics at each update, in [0, 1).
        epsilon: floor of the variance.

    Keyword Args:
        synchronize: average each update's moments over the processes of torch.distributed's
            default group (data-parallel training, where every process updates at once with a
            batch of the same size), so that every process keeps the same statistics, those of
            all the processes' targets together.

    Examples:
        >>> normalizer = ValueNormalizer(decay=0.0)
        >>> normalizer.update(torch.tensor([1.0, 3.0]))
        >>> normalizer.normalize(torch.tensor([1.0, 3.0]))
        tensor([-1.,  1.])
        >>> normalizer.denormalize(torch.tensor([0.0]))
        tensor([2.])
    """

    def __init__(self, decay: float = 0.99, epsilon: float = 1e-4, *, synchronize: bool = False):
        super().__init__()
        if not 0.0 <= decay < 1.0:
            raise ValueError(f"decay must be in [0, 1), got {decay}")
        if epsilon <= 0.0:
            raise ValueError(f"epsilon must be positive, got {epsilon}")
        self.decay = decay
        self.epsilon = epsilon
        self.synchronize = synchronize
        self.register_buffer("mean_estimate", torch.zeros(()))
        self.register_buffer("square_estimate", torch.zeros(()))
        self.register_buffer("weight", torch.zeros(()))

    def extra_repr(self) -> str:
        return f"decay={self.decay}, epsilon={self.epsilon}"

    @torch.no_grad()
    def update(self, targets: Tensor) -> None:
        """Moves the statistics towards the mean and mean square of ``targets`` (any shape).
        Targets with a non-finite value leave them as they were; without reading anything on
        the host, so that a pass that calls it makes no host synchronisation (the non-finite
        targets show in what is computed from them, the losses)."""
        targets = targets.detach().float()
        moments = torch.stack([targets.mean(), targets.square().mean()])
        if self.synchronize:
            dist.all_reduce(moments)
            moments /= dist.get_world_size()
        # non-finite targets make a moment non-finite (with synchronize, on every process
        # alike): the statistics then stay as they were, decided on the device, not the host
        finite = torch.isfinite(moments).all()
        keep = self.decay
        for estimate, moment in (
            (self.mean_estimate, moments[0]),
            (self.square_estimate, moments[1]),
            (self.weight, 1.0),
        ):
            estimate.copy_(torch.where(finite, estimate * keep + (1.0 - keep) * moment, estimate))

    def statistics(self) -> tuple[Tensor, Tensor]:
        """(mean, standard deviation): (0, 1) before the first update."""
        updated = self.weight > 0  # a tensor test: no host synchronisation
        weight = torch.where(updated, self.weight, 1.0)
        mean = self.mean_estimate / weight
        variance = (self.square_estimate / weight - mean.square()).clamp_min(self.epsilon)
        return torch.where(updated, mean, 0.0), torch.where(updated, variance.sqrt(), 1.0)

    def normalize(self, value: Tensor) -> Tensor:
        """Targets in the critics' units."""
        mean, std = self.statistics()
        return ((value - mean) / std).to(value.dtype)

    def denormalize(self, value: Tensor) -> Tensor:
        """Critic outputs in the targets' units."""
        mean, std = self.statistics()
        return (value * std + mean).to(value.dtype)
