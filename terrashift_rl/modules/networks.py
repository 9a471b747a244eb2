"""Actor, value and baseline networks of MA-POCA around one shared trunk.

:func:`make_terrashift_networks` builds every network from one :class:`TerraShiftTrunk` (same
parameters, same ``nn.Module``) and three heads. Keys read and written (* optional: a missing
mask means all present, a missing recurrent state zeros at episode starts):

- ``trunk`` reads ``heightmap``, ``camera`` (with ``camera_channels``), ``objects`` and
  ``objects_mask``* (with ``object_tokens``), ``("agents", "observation")``, ``("agents",
  "mask")``*, ``("agents", "recurrent_state")``*, ``is_init``;
  writes ``("agents", "embedding")`` [B, K, d] and ``("next", "agents", "recurrent_state")``
  [B, K, L, d].
- ``actor`` (trunk + ``policy_head`` + :class:`ScaledBeta`, a torchrl ``ProbabilisticActor``) reads
  the trunk's inputs; writes the trunk's outputs, ``("agents", "concentration1")`` and
  ``("agents", "concentration0")`` [B, K, A], ``("agents", "action")`` [B, K, A] in [-1, 1]
  and ``("agents", "action_log_prob")`` [B, K]. With ``config.distribution="normal"`` the head
  writes ``("agents", "loc")`` and ``("agents", "scale")`` instead, the actor samples torchrl's
  ``IndependentNormal``, and actions may leave [-1, 1] (the simulator clips them).
- ``value_network`` (trunk + ``value_head``) reads the trunk's inputs; writes the trunk's
  outputs and ``state_value`` [B, 1].
- ``baseline_network`` (trunk + ``baseline_head``) reads the trunk's inputs and ``("agents",
  "action")``; writes the trunk's outputs and ``("agents", "baseline")`` [B, K, 1].
- ``value_head`` reads ``("agents", "embedding")`` and ``("agents", "mask")``*; writes
  ``state_value`` [B, 1].
- ``baseline_head`` reads ``("agents", "embedding")``, ``("agents", "action")`` and
  ``("agents", "mask")``*; writes ``("agents", "baseline")`` [B, K, 1].
- with ``critic_objects`` both heads also read ``("privileged", "objects")`` and
  ``("privileged", "objects_mask")``*, the object sequence of a scene with
  ``privileged_objects``; the trunk, and so the actor, never does: a trained actor acts on
  what the trunk reads alone.

How to use the sharing:

- Collection: run ``actor`` (under ``torch.no_grad``, as collectors do); the environment needs
  ``InitTracker`` and the primer from :meth:`TerraShiftNetworks.make_tensordict_primer`.
- Standalone values, e.g. for GAE on collected data: ``value_network`` runs the trunk itself.
  In step mode every element uses the GRU state stored with it at collection, which reproduces
  the collection-time embeddings exactly with no sequence processing; on ``data["next"]`` it
  reads the state stored after each step, so V(s_{t+1}) is exact too. Do not mark next steps
  ``is_init`` where the root step is (torchrl's GAE does so unless ``shifted=True``): with
  stored states that zeroes the memory behind V(s_1) of every episode.
- Loss: the trunk should run once per mini-batch. Call ``actor.get_dist(td)`` (or the actor)
  first: it writes a fresh, differentiable ``("agents", "embedding")`` into ``td``; then run
  ``value_head(td)`` and ``baseline_head(td)``, which read that embedding, so value and baseline
  gradients reach the trunk through the same graph. Running the heads on data whose embedding
  was written at collection instead would read a stale, gradient-free embedding.

The actor's log-probability is joint over the action dims: ``("agents", "action_log_prob")`` is
[B, K], one value per agent, as are the distribution's ``entropy()`` values.
"""

from __future__ import annotations

from typing import Any

from tensordict.nn import TensorDictModule, TensorDictSequential
from torch import nn
from torchrl.envs import TensorDictPrimer
from torchrl.modules import IndependentNormal, ProbabilisticActor

from terrashift_rl.modules import keys
from terrashift_rl.modules.config import TerraShiftModelConfig
from terrashift_rl.modules.critics import CentralValueHead, CounterfactualBaselineHead
from terrashift_rl.modules.distributions import ScaledBeta
from terrashift_rl.modules.policy import BetaPolicyHead, GaussianPolicyHead
from terrashift_rl.modules.trunk import TerraShiftTrunk

__all__ = ["TerraShiftNetworks", "make_terrashift_networks"]


class TerraShiftNetworks(nn.Module):
    """The trunk and heads (as registered submodules) and the actor/value/baseline built on them.

    ``state_dict``, ``parameters``, ``to`` and ``train``/``eval`` of this module cover every
    parameter once. The compositions ``actor``, ``value_network`` and ``baseline_network`` are
    exposed as attributes but not registered, so the shared trunk is not listed three times.

    Attributes:
        trunk: the shared :class:`TerraShiftTrunk`.
        policy_head: writes the Beta concentrations (or the Gaussian's mean and spread) from
            the embedding.
        value_head: writes ``state_value`` from the embedding.
        baseline_head: writes ``("agents", "baseline")`` from the embedding and actions.
        config: the sizes the networks were built with (what further heads are sized by, e.g.
            IPPO's :func:`~terrashift_rl.modules.make_agent_value_head`), or ``None``.
    """

    def __init__(
        self,
        trunk: TerraShiftTrunk,
        policy_head: TensorDictModule,
        value_head: TensorDictModule,
        baseline_head: TensorDictModule,
        *,
        config: TerraShiftModelConfig | None = None,
    ) -> None:
        super().__init__()
        self.config = config
        self.trunk = trunk
        self.policy_head = policy_head
        self.value_head = value_head
        self.baseline_head = baseline_head
        # the distribution the head parameterises, read off what it writes
        if keys.NORMAL_LOC in policy_head.out_keys:
            in_keys = {"loc": keys.NORMAL_LOC, "scale": keys.NORMAL_SCALE}
            distribution_class, distribution_kwargs = IndependentNormal, {}
        else:
            span = 1.0 if config is None else config.action_range
            in_keys = {
                "concentration1": keys.BETA_CONCENTRATION1,
                "concentration0": keys.BETA_CONCENTRATION0,
            }
            distribution_class = ScaledBeta
            distribution_kwargs = {"low": -span, "high": span}
        actor = ProbabilisticActor(
            TensorDictSequential(trunk, policy_head),
            in_keys=in_keys,
            out_keys=[keys.ACTION],
            distribution_class=distribution_class,
            # The parameters are valid by construction; checking them (and every log-prob's
            # argument) would cost a host synchronisation per call and forbid capturing acting
            # and updating as CUDA graphs.
            distribution_kwargs={**distribution_kwargs, "validate_args": False},
            return_log_prob=True,
            log_prob_key=keys.ACTION_LOG_PROB,
        )
        value_network = TensorDictSequential(trunk, value_head)
        baseline_network = TensorDictSequential(trunk, baseline_head)
        # A tuple is not registered as a submodule: the compositions share the modules above.
        self._compositions = (actor, value_network, baseline_network)

    def train(self, mode: bool = True) -> TerraShiftNetworks:
        # The compositions are not submodules; keep their own flags in step with the parts'.
        super().train(mode)
        for composition in self._compositions:
            composition.train(mode)
        return self

    @property
    def actor(self) -> ProbabilisticActor:
        """Trunk + policy head + :class:`ScaledBeta` (or ``IndependentNormal``) sampling; writes
        action and log-prob."""
        return self._compositions[0]

    @property
    def value_network(self) -> TensorDictSequential:
        """Trunk + value head; writes ``state_value`` [B, 1]."""
        return self._compositions[1]

    @property
    def baseline_network(self) -> TensorDictSequential:
        """Trunk + baseline head; reads actions, writes ``("agents", "baseline")`` [B, K, 1]."""
        return self._compositions[2]

    def make_tensordict_primer(
        self, num_agents: int, *, reset_key: str | tuple[str, ...] = "_reset"
    ) -> TensorDictPrimer:
        """The environment primer for the trunk's recurrent state; see the trunk's method."""
        return self.trunk.make_tensordict_primer(num_agents, reset_key=reset_key)

    def compile_networks(self, **options: Any) -> None:
        """``torch.compile`` the tensor-level networks in place; the TensorDict plumbing and the
        GRU memory's loop over time stay eager.

        Unrolled over a 32-step training sequence, the GRU loop takes minutes to compile and
        gains little: each step is already a fused GRU-cell kernel. Every other stage (encoders,
        trunk layers, output MLP, heads) is compiled. Parameter names, and so checkpoints, do
        not change.

        Args:
            options: keyword arguments of :meth:`torch.nn.Module.compile`.
        """
        network = self.trunk.network
        stages = [
            network.heightmap_encoder,
            *([network.object_encoder] if network.object_encoder is not None else []),
            network.agent_encoder,
            *network.layers,
            network.final_norm,
            network.output_mlp,
            *(head.module for head in (self.policy_head, self.value_head, self.baseline_head)),
        ]
        for stage in stages:
            stage.compile(**options)


def make_terrashift_networks(
    config: TerraShiftModelConfig | None = None, *, action_dim: int = 6
) -> TerraShiftNetworks:
    """Build the actor, value and baseline networks around one shared trunk.

    Args:
        config: network sizes; None uses the defaults (Table 1 of the TerraShift paper).
        action_dim: action dims per agent.

    Returns:
        The networks; see the module docstring for the keys each reads and writes.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> networks = make_terrashift_networks(TerraShiftModelConfig.small())
        >>> networks.actor.module[0][0] is networks.value_network[0] is networks.trunk
        True
        >>> data = TensorDict(
        ...     {
        ...         "heightmap": torch.zeros(3, 1, 32, 32),
        ...         "objects": torch.zeros(3, 4, 9),
        ...         "objects_mask": torch.ones(3, 4, dtype=torch.bool),
        ...         "is_init": torch.ones(3, 1, dtype=torch.bool),
        ...         "agents": TensorDict({"observation": torch.zeros(3, 8, 9)}, [3, 8]),
        ...     },
        ...     [3],
        ... )
        >>> with torch.no_grad():
        ...     data = networks.actor(data)
        ...     data = networks.value_head(networks.baseline_head(data))
        >>> data["agents", "action"].shape, data["agents", "action_log_prob"].shape
        (torch.Size([3, 8, 6]), torch.Size([3, 8]))
        >>> data["state_value"].shape, data["agents", "baseline"].shape
        (torch.Size([3, 1]), torch.Size([3, 8, 1]))
    """
    config = TerraShiftModelConfig() if config is None else config
    trunk = TerraShiftTrunk(config)
    if config.distribution == "normal":
        head, head_keys = GaussianPolicyHead, [keys.NORMAL_LOC, keys.NORMAL_SCALE]
    else:
        head, head_keys = BetaPolicyHead, [keys.BETA_CONCENTRATION1, keys.BETA_CONCENTRATION0]
    policy_head = TensorDictModule(
        head(config, action_dim=action_dim), in_keys=[keys.AGENT_EMBEDDING], out_keys=head_keys
    )
    # read by the critics alone: neither the trunk nor the policy head sees them
    privileged = (
        [keys.PRIVILEGED_OBJECTS, keys.PRIVILEGED_OBJECTS_MASK] if config.critic_objects else []
    )
    value_head = TensorDictModule(
        CentralValueHead(config),
        in_keys=[keys.AGENT_EMBEDDING, keys.AGENT_MASK, *privileged],
        out_keys=[keys.STATE_VALUE],
    )
    baseline_head = TensorDictModule(
        CounterfactualBaselineHead(config, action_dim=action_dim),
        in_keys=[keys.AGENT_EMBEDDING, keys.ACTION, keys.AGENT_MASK, *privileged],
        out_keys=[keys.BASELINE],
    )
    return TerraShiftNetworks(trunk, policy_head, value_head, baseline_head, config=config)
