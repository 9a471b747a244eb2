"""A value per agent from the agent's own embedding, the critic of independent PPO (IPPO).

MA-POCA and MAPPO value the team's state by pooling every agent's embedding
(:class:`~terrashift_rl.modules.CentralValueHead`); IPPO (de Witt et al. 2020, "Is Independent
Learning All You Need in the StarCraft Multi-Agent Challenge?") gives each agent its own value
V_i of its own input, here the trunk's embedding of agent i. The trunk's agent self-attention has
already mixed the other agents into that embedding, so V_i sees what agent i's policy sees.
"""

from __future__ import annotations

from tensordict.nn import TensorDictModule
from torch import Tensor, nn

from terrashift_rl.modules import keys
from terrashift_rl.modules.config import TerraShiftModelConfig
from terrashift_rl.modules.layers import feed_forward

__all__ = ["AGENT_VALUE", "AgentValueHead", "make_agent_value_head"]

AGENT_VALUE = ("agents", "state_value")
"""float32 [B, K, 1]: V_i, one value per agent; written by the head of
:func:`make_agent_value_head`."""


class AgentValueHead(nn.Module):
    """V_i(e_i): the same MLP on every agent's embedding, d -> ``critic_hidden_dim`` -> 1.

    Args:
        config: network sizes (``embed_dim``, ``critic_hidden_dim``, ``dropout``).

    Examples:
        >>> import torch
        >>> head = AgentValueHead(TerraShiftModelConfig.small())
        >>> head(torch.randn(5, 8, 32)).shape
        torch.Size([5, 8, 1])
    """

    def __init__(self, config: TerraShiftModelConfig) -> None:
        super().__init__()
        self.mlp = feed_forward(
            config.embed_dim, config.critic_hidden_dim, 1, dropout=config.dropout
        )

    def forward(self, embedding: Tensor) -> Tensor:
        """Values [..., K, 1] of the agent embeddings [..., K, d]."""
        # float32 out, also under bf16 autocast: returns and value losses need the precision
        return self.mlp(embedding).float()


def make_agent_value_head(config: TerraShiftModelConfig) -> TensorDictModule:
    """:class:`AgentValueHead` as a TensorDict module: reads ``("agents", "embedding")``
    [B, K, d], writes :data:`AGENT_VALUE` [B, K, 1].

    Like the other heads, it reads the embedding the trunk wrote into the tensordict: run the
    actor (or the trunk) first, or compose ``TensorDictSequential(networks.trunk, head)``.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> head = make_agent_value_head(TerraShiftModelConfig.small())
        >>> data = TensorDict({("agents", "embedding"): torch.randn(3, 8, 32)}, [3])
        >>> head(data)["agents", "state_value"].shape
        torch.Size([3, 8, 1])
    """
    return TensorDictModule(
        AgentValueHead(config), in_keys=[keys.AGENT_EMBEDDING], out_keys=[AGENT_VALUE]
    )
