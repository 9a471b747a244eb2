"""MA-POCA's centralised value V(s) and counterfactual baselines b_i(s, a_-i).

Both heads read the per-agent embeddings of the shared trunk and pool over the agents that are
present, so they work with any number of agents and ignore absent ones.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from terrashift_rl.modules.config import TerraShiftModelConfig
from terrashift_rl.modules.layers import ResidualSelfAttention, feed_forward, masked_mean

__all__ = ["CentralValueHead", "CounterfactualBaselineHead"]


class CentralValueHead(nn.Module):
    """V(s): residual self-attention over agent embeddings, masked mean over agents, MLP -> 1.

    Args:
        config: network sizes.

    Examples:
        >>> head = CentralValueHead(TerraShiftModelConfig.small())
        >>> head(torch.randn(5, 8, 32)).shape
        torch.Size([5, 1])
    """

    def __init__(self, config: TerraShiftModelConfig) -> None:
        super().__init__()
        self.attention = ResidualSelfAttention(
            config.embed_dim, config.num_heads, dropout=config.dropout
        )
        self.mlp = feed_forward(
            config.embed_dim, config.critic_hidden_dim, 1, dropout=config.dropout
        )

    def forward(self, embedding: Tensor, agent_mask: Tensor | None = None) -> Tensor:
        """Value [..., 1] of agent embeddings [..., K, d] (mask [..., K], True = present)."""
        attended = self.attention(embedding, agent_mask)
        # float32 out, also under bf16 autocast: returns and value losses need the precision
        return self.mlp(masked_mean(attended, agent_mask)).float()


class CounterfactualBaselineHead(nn.Module):
    """b_i: value of the state with agent i's own action marginalised out, for every agent i.

    For agent i the set is ``{g(e_i)} + {f(e_j, a_j) : j != i, j present}`` with
    g: d -> d and f: (d + A) -> d; residual self-attention, masked mean, MLP -> 1. All agents are
    computed at once: a [B, K, K, d] tensor whose row i holds f(e_j, a_j) everywhere except
    g(e_i) at position i, with a key mask that drops absent agents.

    Args:
        config: network sizes.
        action_dim: action dims per agent.

    Examples:
        >>> head = CounterfactualBaselineHead(TerraShiftModelConfig.small(), action_dim=6)
        >>> head(torch.randn(5, 8, 32), torch.rand(5, 8, 6) * 2 - 1).shape
        torch.Size([5, 8, 1])
    """

    def __init__(self, config: TerraShiftModelConfig, *, action_dim: int) -> None:
        super().__init__()
        dim = config.embed_dim
        self.own_state = nn.Linear(dim, dim)
        self.other_state_action = nn.Linear(dim + action_dim, dim)
        self.attention = ResidualSelfAttention(dim, config.num_heads, dropout=config.dropout)
        self.mlp = feed_forward(dim, config.critic_hidden_dim, 1, dropout=config.dropout)

    def forward(
        self, embedding: Tensor, action: Tensor, agent_mask: Tensor | None = None
    ) -> Tensor:
        """Baselines [..., K, 1] from embeddings [..., K, d] and actions [..., K, A]."""
        num_agents = embedding.shape[-2]
        own = self.own_state(embedding)
        others = self.other_state_action(torch.cat([embedding, action.to(embedding.dtype)], -1))
        is_self = torch.eye(num_agents, dtype=torch.bool, device=embedding.device)
        # tokens[..., i, j] = g(e_i) if i == j else f(e_j, a_j)
        tokens = torch.where(is_self[..., None], own.unsqueeze(-2), others.unsqueeze(-3))
        key_mask = None if agent_mask is None else agent_mask.unsqueeze(-2) | is_self
        attended = self.attention(tokens, key_mask)
        return self.mlp(masked_mean(attended, key_mask)).float()  # float32, as the value
