"""The policy heads shared by all agents: embedding -> Beta concentrations, or Gaussian means
and a learned spread, per action dim."""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from terrashift_rl.modules.config import TerraShiftModelConfig
from terrashift_rl.modules.layers import UpdateDropout

__all__ = ["BetaPolicyHead", "GaussianPolicyHead", "initial_concentrations"]


class BetaPolicyHead(nn.Module):
    """MLP (d -> 192 -> 192) with separate alpha and beta heads, one concentration per action dim.

    Concentrations are ``min_concentration + softplus(logit)``; above 1 both, the Beta density is
    unimodal and vanishes at the ends of the action range. The output layers start from
    PyTorch's default initialisation.

    Args:
        config: network sizes.
        action_dim: action dims per agent (6 for TerraShift's wavelet deltas).

    Examples:
        >>> import torch
        >>> head = BetaPolicyHead(TerraShiftModelConfig.small(), action_dim=6)
        >>> alpha, beta = head(torch.randn(2, 8, 32))
        >>> alpha.shape, bool((alpha > 1.01).all() and (beta > 1.01).all())
        (torch.Size([2, 8, 6]), True)
    """

    def __init__(self, config: TerraShiftModelConfig, *, action_dim: int) -> None:
        super().__init__()
        self.mlp = _policy_mlp(config)
        self.alpha_head = _output_layer(config, action_dim)
        self.beta_head = _output_layer(config, action_dim)
        self.min_concentration = config.min_concentration
        if config.initial_action_mean:
            alpha, beta = initial_concentrations(config, action_dim)
            with torch.no_grad():
                self.alpha_head.bias.add_(_inverse_softplus(alpha - config.min_concentration))
                self.beta_head.bias.add_(_inverse_softplus(beta - config.min_concentration))

    def forward(self, embedding: Tensor) -> tuple[Tensor, Tensor]:
        """Map agent embeddings [..., d] to (concentration1, concentration0), each [..., A]."""
        features = self.mlp(embedding)
        # The float32 cast keeps Beta's lgamma-based log-prob and entropy accurate under autocast.
        concentration1 = self.min_concentration + F.softplus(self.alpha_head(features).float())
        concentration0 = self.min_concentration + F.softplus(self.beta_head(features).float())
        return concentration1, concentration0


class GaussianPolicyHead(nn.Module):
    """The same MLP as :class:`BetaPolicyHead` with one mean head, and a state-independent
    standard deviation per action dim (``exp`` of a learned parameter, as in RSL-RL).

    The mean is unbounded: the simulator clips actions to the actuators' [-1, 1], so a mean
    beyond an end acts as that end whatever the spread. The mean layer starts from PyTorch's
    default initialisation, the spread from ``config.initial_std``.

    Args:
        config: network sizes.
        action_dim: action dims per agent.

    Examples:
        >>> import torch
        >>> head = GaussianPolicyHead(TerraShiftModelConfig.small(), action_dim=6)
        >>> loc, scale = head(torch.randn(2, 8, 32))
        >>> loc.shape, scale.shape, round(scale[0, 0, 0].item(), 4)
        (torch.Size([2, 8, 6]), torch.Size([2, 8, 6]), 0.5)
    """

    def __init__(self, config: TerraShiftModelConfig, *, action_dim: int) -> None:
        super().__init__()
        self.mlp = _policy_mlp(config)
        self.mean_head = _output_layer(config, action_dim)
        mean = _initial_action_mean(config, action_dim)
        if mean is not None:
            with torch.no_grad():
                self.mean_head.bias.add_(mean)
        self.log_std = nn.Parameter(torch.full((action_dim,), math.log(config.initial_std)))

    def forward(self, embedding: Tensor) -> tuple[Tensor, Tensor]:
        """Map agent embeddings [..., d] to (mean, standard deviation), each [..., A]."""
        loc = self.mean_head(self.mlp(embedding)).float()
        return loc, self.log_std.exp().expand_as(loc)


def initial_concentrations(config: TerraShiftModelConfig, action_dim: int) -> tuple[Tensor, Tensor]:
    """The Beta that :class:`BetaPolicyHead` starts from where the rest of its output layers
    reads zero: (concentration1, concentration0), each [action_dim]. Centred, both are
    ``min_concentration + log 2`` (softplus of a zero bias); ``config.initial_action_mean``
    keeps the smaller at that and raises the other to put the mean there.

    Examples:
        >>> config = TerraShiftModelConfig.small()
        >>> alpha, beta = initial_concentrations(config, 2)
        >>> [round(v, 3) for v in alpha.tolist()], bool(torch.equal(alpha, beta))
        ([1.703, 1.703], True)
        >>> import dataclasses
        >>> config = dataclasses.replace(config, initial_action_mean=[0.0, -0.5])
        >>> alpha, beta = initial_concentrations(config, 2)
        >>> [round(v, 3) for v in (alpha / (alpha + beta) * 2 - 1).tolist()]  # on [-1, 1]
        [0.0, -0.5]
    """
    centred = config.min_concentration + math.log(2.0)
    mean = _initial_action_mean(config, action_dim)
    if mean is None:
        return torch.full((action_dim,), centred), torch.full((action_dim,), centred)
    unit = (mean / config.action_range + 1.0) / 2.0  # the Beta's mean on [0, 1]
    alpha = centred * torch.clamp(unit / (1.0 - unit), min=1.0)
    beta = centred * torch.clamp((1.0 - unit) / unit, min=1.0)
    return alpha, beta


def _policy_mlp(config: TerraShiftModelConfig) -> nn.Sequential:
    hidden = config.policy_hidden_dim
    return nn.Sequential(
        nn.Linear(config.embed_dim, hidden),
        nn.GELU(),
        UpdateDropout(config.dropout),
        nn.Linear(hidden, hidden),
        nn.GELU(),
    )


def _output_layer(config: TerraShiftModelConfig, action_dim: int) -> nn.Linear:
    return nn.Linear(config.policy_hidden_dim, action_dim)


def _initial_action_mean(config: TerraShiftModelConfig, action_dim: int) -> Tensor | None:
    """``config.initial_action_mean`` as a tensor [action_dim], or None where it is empty."""
    if not config.initial_action_mean:
        return None
    if len(config.initial_action_mean) != action_dim:
        raise ValueError(
            f"initial_action_mean needs one value per action dimension ({action_dim}), got "
            f"{len(config.initial_action_mean)}: {list(config.initial_action_mean)}"
        )
    return torch.tensor(list(config.initial_action_mean), dtype=torch.float32)


def _inverse_softplus(value: Tensor) -> Tensor:
    """The x with softplus(x) = value, for value > 0."""
    return value + torch.log(-torch.expm1(-value))
