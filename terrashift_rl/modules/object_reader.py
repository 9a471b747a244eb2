"""The critics' privileged view: agent embeddings that have read the object sequence handed to
the critics alone (``TerraShiftModelConfig.critic_objects``)."""

from __future__ import annotations

import dataclasses

from torch import Tensor, nn

from terrashift_rl.modules import keys
from terrashift_rl.modules.config import TerraShiftModelConfig
from terrashift_rl.modules.entities import ObjectEncoder
from terrashift_rl.modules.trunk import TrunkLayer

__all__ = ["ObjectReader", "read_objects"]


class ObjectReader(nn.Module):
    """Agent embeddings that have read the object sequence: a critic's privileged view.

    The objects' tokens (an :class:`~terrashift_rl.modules.entities.ObjectEncoder` of its own,
    one token per object), then one :class:`~terrashift_rl.modules.trunk.TrunkLayer` with them
    as its single token set: the agents attend to the objects, then to each other, then a
    feed-forward block, each step residual.

    Args:
        config: network sizes (its object settings aside: one shared token per object).

    Examples:
        >>> import torch
        >>> reader = ObjectReader(TerraShiftModelConfig.small())
        >>> reader(torch.randn(5, 8, 32), torch.randn(5, 4, 9)).shape
        torch.Size([5, 8, 32])
    """

    def __init__(self, config: TerraShiftModelConfig) -> None:
        super().__init__()
        sizes = dataclasses.replace(config, object_tokens=False, relative_objects=False)
        self.object_encoder = ObjectEncoder(sizes)
        self.layer = TrunkLayer(sizes)

    def forward(
        self,
        embedding: Tensor,
        objects: Tensor,
        objects_mask: Tensor | None = None,
        agent_mask: Tensor | None = None,
    ) -> Tensor:
        """Embeddings [..., K, d] updated from objects [..., M, F] (mask [..., M], True =
        active; None: all); absent agents (``agent_mask`` [..., K] False) are not attended."""
        tokens = self.object_encoder(objects, objects_mask)
        return self.layer(embedding, [tokens], [objects_mask], agent_mask)


def read_objects(
    reader: ObjectReader | None,
    embedding: Tensor,
    objects: Tensor | None,
    objects_mask: Tensor | None,
    agent_mask: Tensor | None,
) -> Tensor:
    """``embedding`` after ``reader`` (if any) has read the privileged objects."""
    if reader is None:
        return embedding
    if objects is None:
        raise KeyError(
            f"critics with critic_objects read {keys.PRIVILEGED_OBJECTS}, which the input "
            "lacks: the scene hands it out with privileged_objects=true"
        )
    return reader(embedding, objects, objects_mask, agent_mask)
