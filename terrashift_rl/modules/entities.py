"""Encoders of the per-object and per-agent observation sequences."""

from __future__ import annotations

import torch
from torch import Tensor, nn

from terrashift_rl.modules.config import TerraShiftModelConfig
from terrashift_rl.modules.encodings import sincos_code

__all__ = ["AgentEncoder", "ObjectEncoder"]


class ObjectEncoder(nn.Module):
    """Per-slot MLP (9 -> 64 -> d) plus a fixed 1-D sin-cos code of the slot index.

    Padded slots come out as exact zeros, so their contents cannot matter even to a consumer
    that forgot the mask (the trunk also masks them out of attention).

    With ``config.relative_objects`` the encoder is called with the agents' observations too and
    encodes one token per (agent, slot): the slot's features and the offsets from the agent's
    wavelet to the object and to its goal, straight and the short way round a wrapping grid, so
    each agent reads where things are from where it is.

    Args:
        config: network sizes.

    Examples:
        >>> encoder = ObjectEncoder(TerraShiftModelConfig.small())
        >>> objects, mask = torch.randn(2, 4, 9), torch.tensor([[True, True, False, False]] * 2)
        >>> tokens = encoder(objects, mask)
        >>> tokens.shape, bool(tokens[:, 2:].eq(0).all())
        (torch.Size([2, 4, 32]), True)
    """

    def __init__(self, config: TerraShiftModelConfig) -> None:
        super().__init__()
        self.relative = config.relative_objects
        in_dim = config.object_feature_dim + (8 if self.relative else 0)
        self.mlp = nn.Sequential(
            nn.Linear(in_dim, config.object_hidden_dim),
            nn.GELU(),
            nn.Linear(config.object_hidden_dim, config.embed_dim),
        )

    def forward(
        self,
        objects: Tensor,
        objects_mask: Tensor | None = None,
        agent_observation: Tensor | None = None,
    ) -> Tensor:
        """Encode object slots [B, M, F] (mask [B, M], True = active) into tokens [B, M, d],
        or, with ``relative_objects``, into per-agent tokens [B, K, M, d] given the agents'
        observations [B, K, 9]."""
        if self.relative:
            if agent_observation is None:
                raise ValueError("relative_objects needs the agents' observations")
            agent_xy = agent_observation[..., None, 0:2]  # [B, K, 1, 2]
            offsets = torch.cat(
                [objects[..., None, :, 0:2] - agent_xy, objects[..., None, :, 3:5] - agent_xy],
                dim=-1,
            )
            # the same offsets the short way round a wrapping grid (2 = the platform's width)
            offsets = torch.cat([offsets, offsets - 2.0 * torch.round(0.5 * offsets)], dim=-1)
            per_agent = objects.unsqueeze(-3).expand(*offsets.shape[:-1], objects.shape[-1])
            objects = torch.cat([per_agent, offsets], dim=-1)
            if objects_mask is not None:
                objects_mask = objects_mask.unsqueeze(-2)
        tokens = self.mlp(objects)
        slots = torch.arange(objects.shape[-2], device=objects.device)
        tokens = tokens + sincos_code(slots, tokens.shape[-1]).to(tokens.dtype)
        if objects_mask is not None:
            tokens = tokens.masked_fill(~objects_mask.unsqueeze(-1), 0.0)
        return tokens


class AgentEncoder(nn.Module):
    """Agent MLP (9 -> 128 -> d, LayerNorm and GELU) plus an optional agent-index code.

    The index code is a sinusoidal code of width ``agent_id_dim`` projected to d and added before
    a LayerNorm. It lets agents with identical observations act differently, at the price of
    permutation equivariance; set ``agent_id_code=False`` to make the trunk equivariant in the
    agents. Being sinusoidal, it is defined for any number of agents (8 in pretraining, 16 after).

    Args:
        config: network sizes.

    Examples:
        >>> encoder = AgentEncoder(TerraShiftModelConfig.small())
        >>> encoder(torch.randn(2, 8, 9)).shape
        torch.Size([2, 8, 32])
    """

    def __init__(self, config: TerraShiftModelConfig) -> None:
        super().__init__()
        self.mlp = nn.Sequential(
            nn.Linear(config.agent_observation_dim, config.agent_hidden_dim),
            nn.LayerNorm(config.agent_hidden_dim),
            nn.GELU(),
            nn.Linear(config.agent_hidden_dim, config.embed_dim),
            nn.LayerNorm(config.embed_dim),
            nn.GELU(),
        )
        self.agent_id_dim = config.agent_id_dim
        self.id_projection = (
            nn.Linear(config.agent_id_dim, config.embed_dim) if config.agent_id_code else None
        )
        self.norm = nn.LayerNorm(config.embed_dim)

    def forward(self, agent_observation: Tensor) -> Tensor:
        """Encode agent observations [B, K, 9] into agent embeddings [B, K, d]."""
        embedding = self.mlp(agent_observation)
        if self.id_projection is not None:
            agent_index = torch.arange(agent_observation.shape[-2], device=embedding.device)
            id_code = sincos_code(agent_index, self.agent_id_dim).to(embedding.dtype)
            embedding = embedding + self.id_projection(id_code)
        return self.norm(embedding)
