"""The policy head shared by all agents: embedding -> Beta concentrations per action dim."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from terrashift_rl.modules.config import TerraShiftModelConfig
from terrashift_rl.modules.layers import UpdateDropout

__all__ = ["BetaPolicyHead"]


class BetaPolicyHead(nn.Module):
    """MLP (d -> 192 -> 192) with separate alpha and beta heads, one concentration per action dim.

    Concentrations are ``min_concentration + softplus(logit)``; above 1 both, the Beta density is
    unimodal and vanishes at the ends of the action range. The output layers start from
    PyTorch's default initialisation times ``config.policy_output_gain``.

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
        hidden = config.policy_hidden_dim
        self.mlp = nn.Sequential(
            nn.Linear(config.embed_dim, hidden),
            nn.GELU(),
            UpdateDropout(config.dropout),
            nn.Linear(hidden, hidden),
            nn.GELU(),
        )
        self.alpha_head = nn.Linear(hidden, action_dim)
        self.beta_head = nn.Linear(hidden, action_dim)
        with torch.no_grad():
            for head in (self.alpha_head, self.beta_head):
                head.weight.mul_(config.policy_output_gain)
                head.bias.mul_(config.policy_output_gain)
        self.min_concentration = config.min_concentration

    def forward(self, embedding: Tensor) -> tuple[Tensor, Tensor]:
        """Map agent embeddings [..., d] to (concentration1, concentration0), each [..., A]."""
        features = self.mlp(embedding)
        # The float32 cast keeps Beta's lgamma-based log-prob and entropy accurate under autocast.
        concentration1 = self.min_concentration + F.softplus(self.alpha_head(features).float())
        concentration0 = self.min_concentration + F.softplus(self.beta_head(features).float())
        return concentration1, concentration0
