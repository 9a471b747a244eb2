"""MA-POCA's centralised value V(s) and counterfactual baselines b_i(s, a_-i).

Two networks, as Unity ML-Agents' POCA builds them: V(s) attends over every agent's features
and pools them; agent i's baseline attends over agent i's own features and the other agents'
feature-action pairs, so it sees everyone's action but i's. Both use residual self-attention
and a mean over the agents present, so they take any number of agents and ignore absent ones.

- :class:`CentralValue` and :class:`CounterfactualBaseline` are TensorDict modules for any
  environment with flat per-agent observations ``[*B, K, O]``, built from plain sizes: what to
  hand :class:`~terrashift_rl.objectives.mapoca.MAPOCALoss` in another TorchRL project.
- :class:`CentralValueHead` and :class:`CounterfactualBaselineHead` are the same networks on the
  per-agent embeddings of TerraShift's shared trunk, sized by a :class:`TerraShiftModelConfig`;
  with ``critic_objects`` each first reads the object sequence that the critics alone are
  given (:class:`~terrashift_rl.modules.object_reader.ObjectReader`).
- :class:`AttentionValue` and :class:`AttentionBaseline` are the plain ``nn.Module`` both
  kinds are built from, for inputs of another form (pass your own encoders).
- :mod:`terrashift_rl.modules.mlp_critics` holds cheaper critics of MAPPO's kind for a team of
  a fixed size, on the same keys and input checks as the baselines here.
"""

from __future__ import annotations

from typing import Any

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModule
from tensordict.utils import NestedKey
from torch import Tensor, nn

from terrashift_rl.modules.config import TerraShiftModelConfig
from terrashift_rl.modules.layers import ResidualSelfAttention, UpdateDropout, masked_mean
from terrashift_rl.modules.object_reader import ObjectReader, read_objects

__all__ = [
    "AttentionBaseline",
    "AttentionValue",
    "CentralValue",
    "CentralValueHead",
    "CounterfactualBaseline",
    "CounterfactualBaselineHead",
]


_SPREAD_ROWS = 32
"""Up to this many keys x heads, the attention spreads each head's keys and values over its
own channels (zeros elsewhere) and runs one product per sample over all heads: on the CPU,
batched products of tiny per-head matrices cost more than the zeros. Beyond, one per head."""


def _scaled_scores(products: Tensor, scale: float, attendable: Tensor | None) -> Tensor:
    """``scale * products``, -inf where ``attendable`` (broadcast) is False, in one pass."""
    if attendable is None:
        return products * scale
    key_bias = torch.zeros(attendable.shape, dtype=products.dtype, device=products.device)
    return torch.add(key_bias.masked_fill_(~attendable, float("-inf")), products, alpha=scale)


def _mlp(
    in_dim: int, hidden_dim: int, out_dim: int, *, depth: int, dropout: float
) -> nn.Sequential:
    """``depth`` hidden layers (Linear -> GELU -> dropout), then Linear -> ``out_dim``.

    ``depth=1`` is :func:`~terrashift_rl.modules.layers.feed_forward`, parameter names included.
    """
    if depth < 0:
        raise ValueError(f"depth must be a non-negative number of hidden layers, got {depth}.")
    layers: list[nn.Module] = []
    for layer in range(depth):
        layers += [
            nn.Linear(in_dim if layer == 0 else hidden_dim, hidden_dim),
            nn.GELU(),
            UpdateDropout(dropout),
        ]
    layers.append(nn.Linear(hidden_dim if depth else in_dim, out_dim))
    return nn.Sequential(*layers)


class _AttentionPool(nn.Module):
    """Encoders named by ``encoders``, then residual self-attention over a set of encoded
    elements, masked mean over it, MLP -> 1."""

    def __init__(
        self,
        encoders: dict[str, nn.Module],
        *,
        width: int,
        num_heads: int,
        hidden_dim: int,
        depth: int = 1,
        dropout: float = 0.0,
    ) -> None:
        super().__init__()
        for name, encoder in encoders.items():
            self.add_module(name, encoder)
        self.attention = ResidualSelfAttention(width, num_heads, dropout=dropout)
        self.mlp = _mlp(width, hidden_dim, 1, depth=depth, dropout=dropout)

    def _pool(self, tokens: Tensor, key_mask: Tensor | None) -> Tensor:
        block = self.attention
        attended = block.output_norm(
            tokens + block.attention_dropout(self._attend(tokens, key_mask))
        )
        # float32 out, also under bf16 autocast: returns and value losses need the precision
        return self.mlp(masked_mean(attended, key_mask)).float()

    def _attend(self, tokens: Tensor, key_mask: Tensor | None) -> Tensor:
        """The attention of the residual block over a set of tokens [..., T, width], keys
        masked by ``key_mask`` [..., T]; [..., T, width] out.

        :class:`~terrashift_rl.modules.layers.MultiHeadAttention`'s math (a set without keys
        gives zeros there; here what its masked mean drops), laid out for sets of a few tokens
        on the CPU: the softmax runs over the keys as a leading dim (over a last dim of a few
        entries PyTorch's CPU softmax is many times slower), and for few keys x heads
        (``_SPREAD_ROWS``) the scores and the weighted sum are one product per sample.
        """
        attention = self.attention.attention
        heads = attention.num_heads
        normed = self.attention.input_norm(tokens)
        queries = attention.query_projection(normed)
        keys, values = attention.key_value_projection(normed).chunk(2, -1)
        spread = heads * tokens.shape[-2] <= _SPREAD_ROWS
        if spread:
            # each head's keys and values in its own channels, zeros elsewhere: [..., key *
            # heads, width]
            head_channels = torch.eye(heads, dtype=keys.dtype, device=keys.device)
            head_channels = head_channels.repeat_interleave(keys.shape[-1] // heads, -1)
            keys, values = (
                (x.unsqueeze(-2) * head_channels).flatten(-3, -2) for x in (keys, values)
            )
            products = (keys @ queries.mT).unflatten(-2, (-1, heads))
        else:
            queries, keys, values = (
                x.unflatten(-1, (heads, -1)).transpose(-2, -3) for x in (queries, keys, values)
            )
            products = (keys @ queries.mT).transpose(-2, -3)
        # [..., key, heads, query]
        attendable = None
        if key_mask is not None:
            # a set without any key attends everywhere; the masked mean then drops it whole
            attendable = (key_mask | ~key_mask.any(-1, keepdim=True))[..., None, None]
        weights = _scaled_scores(products, attention.scale, attendable).softmax(-3)
        weights = weights.to(values.dtype)
        if spread:
            attended = weights.flatten(-3, -2).mT @ values
        else:
            # [..., heads, query, channels] -> [..., query, width]
            attended = (weights.movedim(-3, -1) @ values).transpose(-2, -3).flatten(-2)
        return attention.output_projection(attended)


class AttentionValue(_AttentionPool):
    """V(s) of a team: encoder per agent, residual self-attention, masked mean, MLP -> 1.

    Invariant to the order of the agents; absent agents (mask False) change nothing.

    Args:
        encoder: maps one agent's features [..., F] to [..., width].

    Keyword Args:
        sizes: ``width`` (of the encoded agents, required), ``num_heads`` (attention heads,
            dividing ``width``; required), ``hidden_dim`` (width of the hidden layers of the MLP
            after pooling; required), ``depth`` (its hidden layers, 1 by default) and
            ``dropout`` (in backpropagated passes only, see
            :mod:`~terrashift_rl.modules.layers`; 0 by default).

    Examples:
        >>> value = AttentionValue(nn.Linear(5, 16), width=16, num_heads=2, hidden_dim=32)
        >>> value(torch.randn(4, 3, 5)).shape
        torch.Size([4, 1])
    """

    encoder: nn.Module

    def __init__(self, encoder: nn.Module, **sizes: Any) -> None:
        super().__init__({"encoder": encoder}, **sizes)

    def forward(self, features: Tensor, agent_mask: Tensor | None = None) -> Tensor:
        """Value [..., 1] of per-agent features [..., K, F] (mask [..., K], True = present)."""
        return self._pool(self.encoder(features), agent_mask)


class AttentionBaseline(_AttentionPool):
    """b_i: the value of the state with agent i's own action left out, for every agent i.

    For agent i the set is ``{g(x_i)} + {f(x_j, a_j) : j != i, j present}`` with ``g`` the
    ``own_state`` and ``f`` the ``other_state_action`` encoder; residual self-attention, masked
    mean, MLP -> 1. All agents are computed at once, and the encoders run once per agent: the K
    sets share the tokens f(x_j, a_j), so that only the attention weights and what follows
    them are computed per set (the K sets of K tokens are never materialised before the
    attention). A key mask drops absent agents. Permuting the agents permutes the baselines
    alike.

    Args:
        own_state: maps one agent's features [..., F] to [..., width].
        other_state_action: maps one agent's features and action [..., F + A] to [..., width].

    Keyword Args:
        sizes: ``width``, ``num_heads``, ``hidden_dim``, ``depth`` and ``dropout``, as for
            :class:`AttentionValue`.

    Examples:
        >>> baseline = AttentionBaseline(
        ...     nn.Linear(5, 16), nn.Linear(5 + 2, 16), width=16, num_heads=2, hidden_dim=32)
        >>> baseline(torch.randn(4, 3, 5), torch.randn(4, 3, 2)).shape
        torch.Size([4, 3, 1])
    """

    own_state: nn.Module
    other_state_action: nn.Module

    def __init__(self, own_state: nn.Module, other_state_action: nn.Module, **sizes: Any) -> None:
        super().__init__(
            {"own_state": own_state, "other_state_action": other_state_action}, **sizes
        )

    def forward(self, features: Tensor, action: Tensor, agent_mask: Tensor | None = None) -> Tensor:
        """Baselines [..., K, 1] from features [..., K, F] and actions [..., K, A]."""
        num_agents = features.shape[-2]
        own = self.own_state(features)
        others = self.other_state_action(torch.cat([features, action.to(features.dtype)], -1))
        is_self = torch.eye(num_agents, dtype=torch.bool, device=features.device)
        key_mask = None if agent_mask is None else agent_mask.unsqueeze(-2) | is_self
        return self._pool_sets(own, others, is_self, key_mask)

    def _pool_sets(
        self, own: Tensor, others: Tensor, is_self: Tensor, key_mask: Tensor | None
    ) -> Tensor:
        """The residual self-attention over every agent's set, masked mean, MLP.

        The K sets share all but K of their K² tokens, and everything in the block but the
        attention weights and the output norm acts on one token at a time: the input norm and
        the query, key and value projections run once on the 2K distinct tokens g(x_i) and
        f(x_j, a_j), the sets' scores are gathered from their 2K x 2K products, and the value
        of the set's own token enters as a correction of the shared values. Only the attended
        tokens, [..., K, K, width], and the scores, [..., heads, K, K, K], are per set.
        """
        block = self.attention
        attention = block.attention
        num_agents = own.shape[-2]
        # g(x_1..K), then f(x_1..K, a_1..K); token t of agent i's set is number
        # t + K (t's pair) where t != i and i (its own state) where t == i
        normed = block.input_norm(torch.cat([own, others], -2))
        index = torch.arange(num_agents, device=own.device) + num_agents * ~is_self
        queries = attention.query_projection(normed).unflatten(-1, (attention.num_heads, -1))
        keys, values = (
            attention.key_value_projection(normed)
            .unflatten(-1, (2, attention.num_heads, -1))
            .unbind(-3)
        )
        # [..., heads, 2K, channels]
        queries, keys, values = (x.transpose(-2, -3) for x in (queries, keys, values))
        products = queries @ keys.transpose(-1, -2)
        # [..., heads, key u, set i, query t]: the keys outermost, so that the softmax over
        # them runs along contiguous rows of K² entries (over a last dim of K entries, PyTorch's
        # CPU softmax is many times slower)
        scores = products[..., index[None, :, :], index.T[:, :, None]]
        attendable = None if key_mask is None else key_mask.transpose(-1, -2)[..., None, :, :, None]
        scores = _scaled_scores(scores, attention.scale, attendable)
        weights = scores.softmax(-3).to(values.dtype)
        own_values, other_values = values.split(num_agents, -2)
        # [..., heads, channels, set i, query t]
        attended = (other_values.transpose(-1, -2) @ weights.flatten(-2)).unflatten(
            -1, (num_agents, num_agents)
        )
        # set i attends to its own g(x_i) where the shared values hold f(x_i, a_i)
        own_weight = weights.diagonal(dim1=-3, dim2=-2).transpose(-1, -2)
        own_correction = (own_values - other_values).transpose(-1, -2)
        attended = attended + own_weight.unsqueeze(-3) * own_correction.unsqueeze(-1)
        # [..., set i, query t, width]
        attended = attention.output_projection(attended.flatten(-4, -3).movedim(-3, -1))
        # + the sets' tokens: f(x_t, a_t) at [i, t], g(x_i) in place of f(x_i, a_i) at [i, i]
        sets = block.attention_dropout(attended) + others.unsqueeze(-3)
        sets.diagonal(0, -3, -2).add_((own - others).transpose(-1, -2))
        sets = block.output_norm(sets)
        # float32 out, also under bf16 autocast, as the value's
        return self.mlp(masked_mean(sets, key_mask)).float()


class CentralValueHead(AttentionValue):
    """V(s) on the trunk's agent embeddings: residual self-attention, masked mean, MLP -> 1.

    With ``config.critic_objects`` the embeddings first read the privileged object sequence
    (:class:`~terrashift_rl.modules.object_reader.ObjectReader`).

    Args:
        config: network sizes.

    Examples:
        >>> head = CentralValueHead(TerraShiftModelConfig.small())
        >>> head(torch.randn(5, 8, 32)).shape
        torch.Size([5, 1])
        >>> import dataclasses
        >>> config = dataclasses.replace(
        ...     TerraShiftModelConfig.small(), object_tokens=False, critic_objects=True)
        >>> CentralValueHead(config)(torch.randn(5, 8, 32), None, torch.randn(5, 4, 9)).shape
        torch.Size([5, 1])
    """

    def __init__(self, config: TerraShiftModelConfig) -> None:
        super().__init__(
            nn.Identity(),
            width=config.embed_dim,
            num_heads=config.num_heads,
            hidden_dim=config.critic_hidden_dim,
            dropout=config.dropout,
        )
        self.object_reader = ObjectReader(config) if config.critic_objects else None

    def forward(
        self,
        embedding: Tensor,
        agent_mask: Tensor | None = None,
        objects: Tensor | None = None,
        objects_mask: Tensor | None = None,
    ) -> Tensor:
        """Value [..., 1] of embeddings [..., K, d]; ``objects`` [..., M, F] and their mask
        [..., M] are read with ``critic_objects`` (and required then)."""
        features = read_objects(self.object_reader, embedding, objects, objects_mask, agent_mask)
        return super().forward(features, agent_mask)


class CounterfactualBaselineHead(AttentionBaseline):
    """b_i on the trunk's agent embeddings e: g and f are linear maps d -> d and (d + A) -> d.

    With ``config.critic_objects`` the embeddings first read the privileged object sequence
    (:class:`~terrashift_rl.modules.object_reader.ObjectReader`, the head's own).

    Args:
        config: network sizes.
        action_dim: action dims per agent.

    Examples:
        >>> head = CounterfactualBaselineHead(TerraShiftModelConfig.small(), action_dim=6)
        >>> head(torch.randn(5, 8, 32), torch.rand(5, 8, 6) * 2 - 1).shape
        torch.Size([5, 8, 1])
    """

    def __init__(self, config: TerraShiftModelConfig, *, action_dim: int) -> None:
        dim = config.embed_dim
        super().__init__(
            nn.Linear(dim, dim),
            nn.Linear(dim + action_dim, dim),
            width=dim,
            num_heads=config.num_heads,
            hidden_dim=config.critic_hidden_dim,
            dropout=config.dropout,
        )
        self.object_reader = ObjectReader(config) if config.critic_objects else None

    def forward(
        self,
        embedding: Tensor,
        action: Tensor,
        agent_mask: Tensor | None = None,
        objects: Tensor | None = None,
        objects_mask: Tensor | None = None,
    ) -> Tensor:
        """Baselines [..., K, 1] from embeddings [..., K, d] and actions [..., K, A];
        ``objects`` [..., M, F] and their mask [..., M] are read with ``critic_objects`` (and
        required then)."""
        features = read_objects(self.object_reader, embedding, objects, objects_mask, agent_mask)
        return super().forward(features, action, agent_mask)


class CentralValue(TensorDictModule):
    """V(s) for any team with flat per-agent observations, as a TensorDict module.

    Reads ``(group, "observation")`` [*B, K, O] and, if there, ``(group, "mask")`` [*B, K]
    (True where the agent is present; absent means all present); writes ``"state_value"``
    [*B, 1], the keys :class:`~terrashift_rl.objectives.mapoca.MAPOCALoss` reads by default (VMAS's
    too). Each agent's observation goes through an MLP, then :class:`AttentionValue` pools the
    team: no fixed number of agents, no order among them.

    Args:
        observation_dim: O, features per agent.

    Keyword Args:
        width: width of every hidden layer and of the attention.
        depth: hidden layers of the observation encoder and of the MLP after pooling.
        num_heads: attention heads; divides ``width``.
        group: the agents' group.
        observation_key: defaults to ``(group, "observation")``.
        mask_key: defaults to ``(group, "mask")``.
        out_key: where V is written.

    Examples:
        >>> from tensordict import TensorDict
        >>> value = CentralValue(observation_dim=5, width=16, depth=1, num_heads=2)
        >>> data = TensorDict({("agents", "observation"): torch.randn(4, 3, 5)}, [4])
        >>> value(data)["state_value"].shape
        torch.Size([4, 1])
    """

    def __init__(
        self,
        observation_dim: int,
        *,
        width: int = 64,
        depth: int = 2,
        num_heads: int = 4,
        group: str = "agents",
        observation_key: NestedKey | None = None,
        mask_key: NestedKey | None = None,
        out_key: NestedKey = "state_value",
    ) -> None:
        network = AttentionValue(
            _mlp(observation_dim, width, width, depth=depth, dropout=0.0),
            width=width,
            num_heads=num_heads,
            hidden_dim=width,
            depth=depth,
        )
        observation_key = (group, "observation") if observation_key is None else observation_key
        mask_key = (group, "mask") if mask_key is None else mask_key
        super().__init__(network, in_keys=[observation_key, mask_key], out_keys=[out_key])
        self.observation_dim = observation_dim

    def forward(self, tensordict: TensorDictBase, **kwargs) -> TensorDictBase:
        observation_key, mask_key = self.in_keys
        inputs = _agent_inputs(
            tensordict, {observation_key: self.observation_dim}, mask_key, type(self).__name__
        )
        # outputs go to the caller's tensordict, also where the inputs were reshaped in a copy
        return super().forward(inputs, **{"tensordict_out": tensordict, **kwargs})


class _Baseline(TensorDictModule):
    """The keys and input checks of the generic baselines: reads ``(group, "observation")``
    [*B, K, O], ``(group, "action")`` [*B, K, A] (or integer actions [*B, K], one-hot encoded)
    and, if there, ``(group, "mask")`` [*B, K]; writes ``(group, "baseline")`` [*B, K, 1]."""

    def __init__(
        self,
        network: nn.Module,
        observation_dim: int,
        action_dim: int,
        *,
        group: str,
        observation_key: NestedKey | None,
        action_key: NestedKey | None,
        mask_key: NestedKey | None,
        out_key: NestedKey | None,
    ) -> None:
        super().__init__(
            network,
            in_keys=[
                (group, "observation") if observation_key is None else observation_key,
                (group, "action") if action_key is None else action_key,
                (group, "mask") if mask_key is None else mask_key,
            ],
            out_keys=[(group, "baseline") if out_key is None else out_key],
        )
        self.observation_dim = observation_dim
        self.action_dim = action_dim

    def forward(self, tensordict: TensorDictBase, **kwargs) -> TensorDictBase:
        observation_key, action_key, mask_key = self.in_keys
        inputs = _agent_inputs(
            tensordict,
            {observation_key: self.observation_dim, action_key: self.action_dim},
            mask_key,
            type(self).__name__,
            categorical_key=action_key,
        )
        return super().forward(inputs, **{"tensordict_out": tensordict, **kwargs})


class CounterfactualBaseline(_Baseline):
    """Counterfactual baselines b_i for any team with flat per-agent observations.

    Reads ``(group, "observation")`` [*B, K, O], ``(group, "action")`` [*B, K, A] (or integer
    actions [*B, K] of a categorical spec, one-hot encoded over ``action_dim`` classes) and, if
    there, ``(group, "mask")`` [*B, K]; writes ``(group, "baseline")`` [*B, K, 1]. Agent i's
    observation goes through an MLP g, every other agent's observation and action through an MLP
    f, and :class:`AttentionBaseline` attends over ``{g(o_i)} + {f(o_j, a_j) : j != i}``:
    ML-Agents' POCA baseline, for any number of agents.

    Args:
        observation_dim: O, features per agent.
        action_dim: A, action dims per agent (classes for integer actions).

    Keyword Args:
        width: width of every hidden layer and of the attention.
        depth: hidden layers of the two encoders and of the MLP after pooling.
        num_heads: attention heads; divides ``width``.
        group: the agents' group.
        observation_key: defaults to ``(group, "observation")``.
        action_key: defaults to ``(group, "action")``.
        mask_key: defaults to ``(group, "mask")``.
        out_key: defaults to ``(group, "baseline")``.

    Examples:
        >>> from tensordict import TensorDict
        >>> baseline = CounterfactualBaseline(5, 2, width=16, depth=1, num_heads=2)
        >>> data = TensorDict({
        ...     ("agents", "observation"): torch.randn(4, 3, 5),
        ...     ("agents", "action"): torch.randn(4, 3, 2)}, [4])
        >>> baseline(data)["agents", "baseline"].shape
        torch.Size([4, 3, 1])
    """

    def __init__(
        self,
        observation_dim: int,
        action_dim: int,
        *,
        width: int = 64,
        depth: int = 2,
        num_heads: int = 4,
        group: str = "agents",
        observation_key: NestedKey | None = None,
        action_key: NestedKey | None = None,
        mask_key: NestedKey | None = None,
        out_key: NestedKey | None = None,
    ) -> None:
        network = AttentionBaseline(
            _mlp(observation_dim, width, width, depth=depth, dropout=0.0),
            _mlp(observation_dim + action_dim, width, width, depth=depth, dropout=0.0),
            width=width,
            num_heads=num_heads,
            hidden_dim=width,
            depth=depth,
        )
        super().__init__(
            network,
            observation_dim,
            action_dim,
            group=group,
            observation_key=observation_key,
            action_key=action_key,
            mask_key=mask_key,
            out_key=out_key,
        )


def _agent_inputs(
    tensordict: TensorDictBase,
    features: dict[NestedKey, int],
    mask_key: NestedKey,
    network: str,
    *,
    categorical_key: NestedKey | None = None,
) -> TensorDictBase:
    """The inputs of a generic critic, checked; an error names the key of any that is missing or
    mis-shaped.

    Every key of ``features`` must hold [*B, K, F], F as given, one [*B, K] for all; integer
    values [*B, K] at ``categorical_key`` are one-hot encoded over its F classes. The mask, when
    there, is [*B, K] or [*B, K, 1]. Returns ``tensordict`` itself, or a shallow copy holding
    the one-hot actions and the mask as bool [*B, K].
    """
    inputs = tensordict
    agent_shape = None
    for key, dim in features.items():
        value = tensordict.get(key, None)
        if value is None:
            raise KeyError(f"{network} reads {key!r}, [*B, K, {dim}]; the input has no such key.")
        if agent_shape is None:
            agent_shape = value.shape[:-1]
        if key == categorical_key and not value.is_floating_point() and value.shape == agent_shape:
            value = nn.functional.one_hot(value.long(), dim).float()
            inputs = inputs.copy().set(key, value)
        if value.ndim < 2 or value.shape[-1] != dim or value.shape[:-1] != agent_shape:
            raise ValueError(
                f"{network} reads {key!r} as [*B, K, {dim}] with [*B, K] = {list(agent_shape)} "
                f"for every input, got {list(value.shape)}."
            )
    mask = tensordict.get(mask_key, None)
    if mask is None:
        return inputs
    if mask.shape not in (agent_shape, (*agent_shape, 1)):
        raise ValueError(
            f"{network} reads the agent mask {mask_key!r} as [*B, K] = {list(agent_shape)} "
            f"(or [*B, K, 1]), got {list(mask.shape)}."
        )
    if mask.shape != agent_shape or mask.dtype != torch.bool:
        inputs = inputs.copy().set(mask_key, mask.reshape(agent_shape).bool())
    return inputs
