"""The shared embedding trunk: observations -> per-agent embeddings with recurrent memory.

:class:`SharedEmbeddingNetwork` is the tensor-level network (Algorithm 2 of the TerraShift paper);
:class:`TerraShiftTrunk` wraps it as a TensorDict module that follows torchrl's recurrent
conventions (those of :class:`torchrl.modules.GRUModule`):

- the GRU state lives in the tensordict at ``("agents", "recurrent_state")``, shape
  [B, K, L, d], and the state after the step is written at ``("next", "agents",
  "recurrent_state")``, so ``env.rollout`` and collectors carry it from step to step once the
  environment has the primer from :meth:`TerraShiftTrunk.make_tensordict_primer`;
- the state is zeroed where ``"is_init"`` is True (torchrl's InitTracker marks episode starts);
- by default every tensordict element is an independent step (collection). Under
  ``torchrl.modules.set_recurrent_mode(True)`` (which torchrl losses set) the last batch dim is
  time: the GRU starts each row from the state stored at its first step and runs over the whole
  sequence, resetting wherever ``is_init`` is set. In this mode too the per-step states after each
  step are written at ``("next", "agents", "recurrent_state")``; they equal what step-by-step
  execution from the same start state writes.

torchrl's GRU modules have no agent dimension; here the agents of every environment are folded
into the GRU's batch.
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torch import Tensor, nn
from torchrl.data import Composite, Unbounded
from torchrl.envs import TensorDictPrimer
from torchrl.modules import recurrent_mode

from terrashift_rl.modules import keys
from terrashift_rl.modules.config import TerraShiftModelConfig
from terrashift_rl.modules.entities import AgentEncoder, ObjectEncoder
from terrashift_rl.modules.heightmap import HeightmapEncoder, stack_camera
from terrashift_rl.modules.layers import MultiHeadAttention, UpdateDropout, feed_forward

__all__ = [
    "AgentMemory",
    "ParallelCrossAttention",
    "SharedEmbeddingNetwork",
    "TerraShiftTrunk",
    "TrunkLayer",
]


class ParallelCrossAttention(nn.Module):
    """Agents attend to several token sets at once; a learned softmax gate mixes the results.

    Each set has its own attention and a scalar gate logit computed from what each agent read in
    that set (a single set has no gate). Sets an environment has no valid token in (e.g. no
    active object) get no weight.
    A set is shared by all agents ([B, N, d], mask [B, N]) or holds each agent's own tokens
    ([B, K, N, d], mask [B, 1, N] or [B, K, N]).

    Args:
        embed_dim: width of agents and tokens.
        num_heads: attention heads per set.
        num_sets: number of token sets.

    Examples:
        >>> fusion = ParallelCrossAttention(8, 2, num_sets=2)
        >>> agents, spatial = torch.randn(3, 4, 8), torch.randn(3, 5, 8)
        >>> objects = torch.randn(3, 2, 8)
        >>> fusion(agents, [spatial, objects], [None, torch.ones(3, 2, dtype=torch.bool)]).shape
        torch.Size([3, 4, 8])
    """

    def __init__(self, embed_dim: int, num_heads: int, *, num_sets: int) -> None:
        super().__init__()
        self.attentions = nn.ModuleList(
            MultiHeadAttention(embed_dim, num_heads) for _ in range(num_sets)
        )
        # one set has nothing to be mixed with: no gate
        self.gates = nn.ModuleList(
            nn.Linear(embed_dim, 1) for _ in range(num_sets if num_sets > 1 else 0)
        )

    def forward(
        self, agents: Tensor, token_sets: list[Tensor], token_masks: list[Tensor | None]
    ) -> Tensor:
        """Fuse agents [B, K, d] with each set [B, N_s, d] or [B, K, N_s, d] (mask or None)."""
        attended = []
        empties = []
        for attention, tokens, mask in zip(self.attentions, token_sets, token_masks, strict=True):
            if tokens.dim() > agents.dim():  # each agent's own set: one query per agent
                read = attention(agents.unsqueeze(-2), tokens, mask).squeeze(-2)
                empty = None if mask is None else ~mask.any(-1)[..., None]  # [B, 1 or K, 1]
            else:
                read = attention(agents, tokens, mask)
                empty = None if mask is None else ~mask.any(-1)[..., None, None]  # [B, 1, 1]
            attended.append(read)
            empties.append(empty)
        if not self.gates:
            return attended[0]
        gate_logits = []
        for gate, read, empty in zip(self.gates, attended, empties, strict=True):
            logit = gate(read)
            if empty is not None:
                logit = logit.masked_fill(empty, float("-inf"))
            gate_logits.append(logit)
        weights = torch.softmax(torch.cat(gate_logits, dim=-1), dim=-1)
        return (torch.stack(attended, dim=-1) * weights.unsqueeze(-2)).sum(-1)


class TrunkLayer(nn.Module):
    """One pre-norm trunk layer: parallel cross-attention, agent self-attention, feed-forward.

    Args:
        config: network sizes.

    Examples:
        >>> layer = TrunkLayer(TerraShiftModelConfig.small())
        >>> agents, spatial = torch.randn(3, 4, 32), torch.randn(3, 5, 32)
        >>> objects = torch.randn(3, 2, 32)
        >>> layer(agents, [spatial, objects], [None, None], None).shape
        torch.Size([3, 4, 32])
    """

    def __init__(self, config: TerraShiftModelConfig) -> None:
        super().__init__()
        dim = config.embed_dim
        self.cross_attention_norm = nn.LayerNorm(dim)
        self.cross_attention = ParallelCrossAttention(
            dim, config.num_heads, num_sets=2 if config.object_tokens else 1
        )
        self.self_attention_norm = nn.LayerNorm(dim)
        self.self_attention = MultiHeadAttention(dim, config.num_heads)
        self.feed_forward_norm = nn.LayerNorm(dim)
        self.feed_forward = feed_forward(dim, config.ffn_dim, dim, dropout=config.dropout)
        self.residual_dropout = UpdateDropout(config.dropout)

    def forward(
        self,
        agents: Tensor,
        token_sets: list[Tensor],
        token_masks: list[Tensor | None],
        agent_mask: Tensor | None,
    ) -> Tensor:
        """Update agents [B, K, d]; absent agents (``agent_mask`` False) are never attended."""
        fused = self.cross_attention(self.cross_attention_norm(agents), token_sets, token_masks)
        agents = agents + self.residual_dropout(fused)
        normed = self.self_attention_norm(agents)
        agents = agents + self.residual_dropout(self.self_attention(normed, normed, agent_mask))
        return agents + self.residual_dropout(self.feed_forward(self.feed_forward_norm(agents)))


class AgentMemory(nn.Module):
    """Stacked GRU cells with a gated residual; every row is one agent of one environment.

    Output: ``x + sigmoid(W [x, h]) * h`` with h the top GRU layer's output, so an untrained
    memory passes the trunk's features through. Dropout acts between GRU layers in update passes.

    Args:
        embed_dim: input and hidden width d.
        num_layers: stacked GRU layers L.
        dropout: dropout between GRU layers (update passes only).

    Examples:
        >>> memory = AgentMemory(8, num_layers=2)
        >>> inputs, state = torch.randn(5, 3, 8), torch.zeros(5, 2, 8)
        >>> outputs, states = memory(inputs, state, torch.zeros(5, 3, dtype=torch.bool))
        >>> outputs.shape, states.shape
        (torch.Size([5, 3, 8]), torch.Size([5, 3, 2, 8]))
    """

    def __init__(self, embed_dim: int, *, num_layers: int, dropout: float = 0.0) -> None:
        super().__init__()
        self.cells = nn.ModuleList(nn.GRUCell(embed_dim, embed_dim) for _ in range(num_layers))
        self.layer_dropout = UpdateDropout(dropout)
        self.gate = nn.Linear(2 * embed_dim, embed_dim)

    def forward(self, inputs: Tensor, state: Tensor, is_init: Tensor) -> tuple[Tensor, Tensor]:
        """Run rows of T steps.

        The loop over time is explicit (no cuDNN sequence call) so resets inside a sequence,
        ``torch.compile`` and ``vmap`` need no data-dependent branching.

        Args:
            inputs: features [R, T, d].
            state: GRU state before the first step [R, L, d].
            is_init: bool [R, T]; the state is zeroed before every step where it is True.

        Returns:
            The outputs [R, T, d] and the state after each step [R, T, L, d].
        """
        hidden = list(state.unbind(-2))
        top_outputs = []
        states = []
        for step in range(inputs.shape[-2]):
            reset = is_init[:, step, None]
            layer_input = inputs[:, step]
            for layer, cell in enumerate(self.cells):
                if layer:
                    layer_input = self.layer_dropout(layer_input)
                previous = torch.where(reset, 0.0, hidden[layer]).to(layer_input.dtype)
                hidden[layer] = cell(layer_input, previous)
                layer_input = hidden[layer]
            top_outputs.append(layer_input)
            states.append(torch.stack(hidden, dim=-2))
        memory = torch.stack(top_outputs, dim=-2).to(inputs.dtype)
        gate = torch.sigmoid(self.gate(torch.cat([inputs, memory], dim=-1)))
        return inputs + gate * memory, torch.stack(states, dim=-3)


class SharedEmbeddingNetwork(nn.Module):
    """Tensor-level trunk: heightmap, objects and agents -> per-agent embeddings and GRU state.

    Heightmap encoder and object encoder produce the spatial and object token sets once per
    environment step (the object set once per agent with ``relative_objects``; none without
    ``object_tokens``; with ``camera_channels`` the heightmap encoder reads the camera as
    further channels, see :func:`~terrashift_rl.modules.heightmap.stack_camera`); the agent
    encoder gives the agent queries; ``trunk_layers`` layers of
    parallel cross-attention (agents -> both sets, softmax-gated), agent self-attention and a
    feed-forward block follow; then a final LayerNorm, an MLP (d -> 192 -> d) and the GRU memory.

    Args:
        config: network sizes.

    Examples:
        >>> network = SharedEmbeddingNetwork(TerraShiftModelConfig.small())
        >>> embedding, state = network(
        ...     torch.zeros(3, 1, 32, 32), torch.zeros(3, 4, 9), torch.zeros(3, 8, 9)
        ... )
        >>> embedding.shape, state.shape
        (torch.Size([3, 8, 32]), torch.Size([3, 8, 2, 32]))
    """

    def __init__(self, config: TerraShiftModelConfig) -> None:
        super().__init__()
        self.embed_dim = config.embed_dim
        self.gru_layers = config.gru_layers
        self.heightmap_encoder = HeightmapEncoder(config)
        self.object_encoder = ObjectEncoder(config) if config.object_tokens else None
        self.camera_channels = config.camera_channels
        self.agent_encoder = AgentEncoder(config)
        self.layers = nn.ModuleList(TrunkLayer(config) for _ in range(config.trunk_layers))
        self.final_norm = nn.LayerNorm(config.embed_dim)
        self.output_mlp = feed_forward(
            config.embed_dim, config.output_hidden_dim, config.embed_dim, dropout=config.dropout
        )
        self.memory = AgentMemory(
            config.embed_dim, num_layers=config.gru_layers, dropout=config.dropout
        )

    def forward(
        self,
        heightmap: Tensor,
        objects: Tensor | None,
        agent_observation: Tensor,
        objects_mask: Tensor | None = None,
        agent_mask: Tensor | None = None,
        recurrent_state: Tensor | None = None,
        is_init: Tensor | None = None,
        *,
        camera: Tensor | None = None,
        sequence: bool = False,
    ) -> tuple[Tensor, Tensor]:
        """Embed a batch of environment steps.

        Args:
            heightmap: [*B, C, H, W].
            objects: [*B, M, F]; None (and unread) without ``object_tokens``.
            agent_observation: [*B, K, 9]; its leading dims define the batch dims B.
            objects_mask: bool [*B, M], True for active slots; None means all active.
            agent_mask: bool [*B, K], True for present agents; None means all present.
            recurrent_state: GRU state before each step [*B, K, L, d]; None means zeros. With
                ``sequence=True`` only the first step's entry of each sequence is used.
            is_init: bool [*B, 1], True at episode starts (state zeroed); None means no reset.
            camera: [*B, C', H', W'] in [0, 1], required with ``camera_channels`` (and unread
                without).
            sequence: whether the last batch dim is time (recurrent mode).

        Returns:
            The embeddings [*B, K, d] and the GRU state after each step [*B, K, L, d].
        """
        batch_shape = agent_observation.shape[:-2]
        num_agents = agent_observation.shape[-2]
        steps = batch_shape[-1] if sequence and batch_shape else 1
        flat = batch_shape.numel()
        rows = flat // steps

        images = heightmap.reshape(flat, *heightmap.shape[-3:])
        if self.camera_channels:
            if camera is None:
                raise ValueError("this trunk has camera_channels but was given no camera")
            images = stack_camera(images, camera.reshape(flat, *camera.shape[-3:]))
        token_sets, token_masks = [self.heightmap_encoder(images)], [None]
        agent_observation = agent_observation.reshape(flat, num_agents, -1)
        if self.object_encoder is not None:
            objects_flat = objects.reshape(flat, *objects.shape[-2:])
            if objects_mask is not None:
                objects_mask = objects_mask.reshape(flat, -1)
            object_tokens = self.object_encoder(objects_flat, objects_mask, agent_observation)
            if objects_mask is not None and object_tokens.dim() == 4:  # per-agent tokens
                objects_mask = objects_mask.unsqueeze(-2)
            token_sets.append(object_tokens)
            token_masks.append(objects_mask)
        if agent_mask is not None:
            agent_mask = agent_mask.reshape(flat, num_agents)
        agents = self.agent_encoder(agent_observation)
        for layer in self.layers:
            agents = layer(agents, token_sets, token_masks, agent_mask)
        agents = self.output_mlp(self.final_norm(agents))

        # Fold agents into the GRU batch: rows of one agent over the T steps of a sequence.
        memory_input = (
            agents.reshape(rows, steps, num_agents, -1)
            .transpose(1, 2)
            .reshape(rows * num_agents, steps, -1)
        )
        if recurrent_state is None:
            start_state = agents.new_zeros(rows * num_agents, self.gru_layers, self.embed_dim)
        else:
            start_state = recurrent_state.reshape(
                rows, steps, num_agents, *recurrent_state.shape[-2:]
            )
            start_state = start_state[:, 0].reshape(rows * num_agents, *recurrent_state.shape[-2:])
        if is_init is None:
            resets = torch.zeros(rows * num_agents, steps, dtype=torch.bool, device=agents.device)
        else:
            resets = (
                is_init.reshape(rows, 1, steps)
                .expand(rows, num_agents, steps)
                .reshape(rows * num_agents, steps)
            )
        memory_output, states = self.memory(memory_input, start_state, resets)

        embedding = (
            memory_output.reshape(rows, num_agents, steps, -1)
            .transpose(1, 2)
            .reshape(*batch_shape, num_agents, -1)
        )
        states = (
            states.reshape(rows, num_agents, steps, self.gru_layers, -1)
            .transpose(1, 2)
            .reshape(*batch_shape, num_agents, self.gru_layers, -1)
        )
        # The state is stored in float32 whatever the autocast dtype, as the primer declares.
        return embedding, states.float()


class TerraShiftTrunk(TensorDictModuleBase):
    """TensorDict wrapper of :class:`SharedEmbeddingNetwork` with torchrl's recurrent conventions.

    Reads ``"heightmap"``, ``"camera"`` (with ``camera_channels``), ``"objects"`` and
    ``"objects_mask"`` (optional; both only with ``object_tokens``), ``("agents",
    "observation")``, ``("agents", "mask")`` (optional), ``("agents", "recurrent_state")``
    (optional: zeros) and ``"is_init"`` (required whenever a recurrent state is present).
    Writes ``("agents", "embedding")`` [B, K, d] and ``("next", "agents", "recurrent_state")``
    [B, K, L, d]. See the module docstring for step and recurrent (sequence) modes.

    Args:
        config: network sizes.

    Examples:
        >>> from tensordict import TensorDict
        >>> trunk = TerraShiftTrunk(TerraShiftModelConfig.small())
        >>> data = TensorDict(
        ...     {
        ...         "heightmap": torch.zeros(3, 1, 32, 32),
        ...         "objects": torch.zeros(3, 4, 9),
        ...         "agents": TensorDict({"observation": torch.zeros(3, 8, 9)}, [3, 8]),
        ...     },
        ...     [3],
        ... )
        >>> trunk(data)["agents", "embedding"].shape
        torch.Size([3, 8, 32])
        >>> data["next", "agents", "recurrent_state"].shape
        torch.Size([3, 8, 2, 32])
    """

    def __init__(self, config: TerraShiftModelConfig) -> None:
        super().__init__()
        self.network = SharedEmbeddingNetwork(config)
        self.in_keys = [
            keys.HEIGHTMAP,
            *([keys.CAMERA] if config.camera_channels else []),
            *([keys.OBJECTS, keys.OBJECTS_MASK] if config.object_tokens else []),
            keys.AGENT_OBSERVATION,
            keys.AGENT_MASK,
            keys.RECURRENT_STATE,
            keys.IS_INIT,
        ]
        self.out_keys = [keys.AGENT_EMBEDDING, keys.NEXT_RECURRENT_STATE]

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        recurrent_state = tensordict.get(keys.RECURRENT_STATE, None)
        is_init = tensordict.get(keys.IS_INIT, None)
        sequence = bool(recurrent_mode())
        if recurrent_state is not None and is_init is None:
            raise KeyError(
                f"{keys.RECURRENT_STATE} is present but {keys.IS_INIT!r} is not: add "
                "torchrl.envs.InitTracker to the environment so episode starts reset the memory."
            )
        if recurrent_state is None and is_init is not None and not torch.compiler.is_compiling():
            # Zeros are the right start state only at episode starts; anywhere else a missing
            # state means the environment drops it between steps and the memory is silently off.
            first_steps = is_init[..., 0, :] if sequence else is_init
            if not bool(first_steps.all()):
                raise KeyError(
                    f"{keys.RECURRENT_STATE} is missing in the middle of an episode: append "
                    "make_tensordict_primer(num_agents) after InitTracker in the environment's "
                    "transforms so the GRU state is carried from step to step."
                )
        network = self.network
        embedding, next_state = network(
            tensordict.get(keys.HEIGHTMAP),
            tensordict.get(keys.OBJECTS) if network.object_encoder is not None else None,
            tensordict.get(keys.AGENT_OBSERVATION),
            objects_mask=tensordict.get(keys.OBJECTS_MASK, None),
            agent_mask=tensordict.get(keys.AGENT_MASK, None),
            recurrent_state=recurrent_state,
            is_init=is_init,
            camera=tensordict.get(keys.CAMERA) if network.camera_channels else None,
            sequence=sequence,
        )
        tensordict.set(keys.AGENT_EMBEDDING, embedding)
        tensordict.set(keys.NEXT_RECURRENT_STATE, next_state)
        return tensordict

    def make_tensordict_primer(
        self, num_agents: int, *, reset_key: str | tuple[str, ...] = "_reset"
    ) -> TensorDictPrimer:
        """A primer that registers ``("agents", "recurrent_state")`` in the environment's specs.

        With it, resets fill the state with zeros and ``step_mdp`` carries ``("next", "agents",
        "recurrent_state")`` to the root between steps. Append it after an ``InitTracker``.

        Args:
            num_agents: agents K of the environment (the state has one GRU state per agent).
            reset_key: the environment's root partial-reset key; TerraShift has agent-level done
                keys too, so torchrl cannot pick one by itself.

        Examples:
            >>> trunk = TerraShiftTrunk(TerraShiftModelConfig.small())
            >>> primer = trunk.make_tensordict_primer(8)
            >>> primer.primers["agents", "recurrent_state"].shape
            torch.Size([8, 2, 32])
        """
        state_spec = Unbounded(shape=(num_agents, self.network.gru_layers, self.network.embed_dim))
        agents_spec = Composite({keys.RECURRENT_STATE[-1]: state_spec}, shape=(num_agents,))
        return TensorDictPrimer(
            {keys.RECURRENT_STATE[0]: agents_spec}, expand_specs=True, reset_key=reset_key
        )
