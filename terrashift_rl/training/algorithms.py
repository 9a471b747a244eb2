"""The on-policy algorithms the trainer runs: each a loss built on the shared networks.

:data:`ALGORITHMS` maps ``algo`` to the algorithm's loss settings, which build an
:class:`Algorithm` on the networks (:meth:`LossConfig.make`). All three share the trunk and the
Beta policy head, and the trainer's loop (collection, one value-estimation pass, epochs of
mini-batches, schedules, critic warm-up, checkpoints) is the same for each; only the critic and
the loss differ:

- ``mapoca``: :class:`~terrashift_rl.objectives.MAPOCALoss`, the centralised value V(s) for the
  returns and a counterfactual baseline b_i(s, a_-i) per agent for the advantages.
- ``mappo``: torchrl's :class:`~torchrl.objectives.multiagent.MAPPOLoss` (clipped PPO) with the
  same centralised value V(s), given to every agent: A_i is the team's GAE advantage.
- ``ippo``: torchrl's :class:`~torchrl.objectives.multiagent.IPPOLoss` with a value V_i per agent
  on its own embedding (:func:`~terrashift_rl.modules.make_agent_value_head`): A_i is agent i's
  GAE advantage from V_i.

Each algorithm owns its loss settings, a :class:`LossConfig` subclass (as BenchMARL's
``MappoConfig``): the ``algo`` config group picks it, and the ``loss`` group holds its fields, so a
setting of another algorithm (MA-POCA's ``baseline_coeff`` or teacher for MAPPO) is refused by
name. A new algorithm is its settings class with a ``make`` method here, its entry in
:data:`ALGORITHMS` and a file in ``recipes/configs/algo/``.

For MAPPO and IPPO the value-estimation pass is :class:`EmbeddingCriticEstimate`: it runs the
trunk and the critic in step mode, as MA-POCA's estimator does, and hands the values to the
loss's torchrl :class:`~torchrl.objectives.value.MultiAgentGAE`, which broadcasts the team's done
flags over the agents and computes per-agent advantages and returns. The settings mean the same
for every algorithm (value normalisation, advantages standardised once per collected batch,
value clipping, the coefficients); ``baseline_coeff`` and the teacher are MA-POCA's alone.
MA-POCA standardises the advantages over every agent at once, MultiAgentGAE each agent's over its
own (torchrl's multi-agent convention; the agents share their networks, so the two differ
little).

Two diagnostics differ in kind: torchrl's ``kl_approx`` is the mean log-ratio log π_old - log π
(unbiased, but a mini-batch's may be negative), MA-POCA's Schulman's non-negative k3 estimate of
the same KL divergence; torchrl's ``explained_variance`` and ``ESS`` are per step and agent, over
a mini-batch's environments (the trainer logs their mean).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import ClassVar

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModule, TensorDictSequential
from torch import Tensor, nn
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.modules import set_recurrent_mode
from torchrl.objectives import LossModule, ValueEstimators
from torchrl.objectives.multiagent import IPPOLoss, MAPPOLoss
from torchrl.objectives.value import MultiAgentGAE

from terrashift_rl.fields import above, at_least, check_fields, interval, setting
from terrashift_rl.modules import TerraShiftNetworks, keys, make_agent_value_head
from terrashift_rl.modules.independent import AGENT_VALUE
from terrashift_rl.objectives import MAPOCALoss, ValueNormalizer
from terrashift_rl.training import distributed

__all__ = [
    "ALGORITHMS",
    "Algorithm",
    "EmbeddingCriticEstimate",
    "IPPOConfig",
    "LossConfig",
    "MAPOCAConfig",
    "MAPPOConfig",
]

VALUE_TARGET = ("agents", "value_target")
"""float32 [B, K, 1]: MAPPO's and IPPO's per-agent returns, in the critic's units."""
ADVANTAGE = ("agents", "advantage")
"""float32 [B, K, 1]: per-agent advantages, standardised over the collected batch."""


@dataclass
class LossConfig:
    """Loss settings every algorithm has (the ``loss`` config group); start/end pairs are linear
    schedules over ``train.schedule_iterations`` updates. A subclass per algorithm adds its own
    and builds the algorithm (:meth:`make`)."""

    algo: ClassVar[str]
    """The ``algo`` config group's option (``loss.algo``) that picks this class."""

    gamma: float = setting(0.95, interval(0, 1, low_open=True))
    """Discount."""
    lmbda: float = setting(0.92, interval(0, 1))
    """GAE lambda."""
    clip_epsilon_start: float = setting(0.2, interval(0, 1, low_open=True, high_open=True))
    """Clip range of the policy's probability ratio (the loss's ``clip_epsilon``) at the start."""
    clip_epsilon_end: float = setting(0.1, interval(0, 1, low_open=True, high_open=True))
    """Clip range of the probability ratio after ``schedule_iterations`` updates."""
    entropy_coeff_start: float = setting(0.002, at_least(0))
    """Weight of the entropy bonus (the loss's ``entropy_coeff``) at the start."""
    entropy_coeff_end: float = setting(0.002, at_least(0))
    """Weight of the entropy bonus after ``schedule_iterations`` updates."""
    clip_value_start: float = setting(0.3, above(0))
    """Clip range of the critics' estimates around those at collection (the loss's
    ``clip_value``, as in torchrl's ``ClipPPOLoss``) at the start."""
    clip_value_end: float = setting(0.1, above(0))
    """Clip range of the critics' estimates after ``schedule_iterations`` updates."""
    value_coeff: float = setting(1.0, at_least(0))
    """Weight of the value loss."""
    normalize_value: bool = setting(True)
    """Train the critics on running-normalised returns (ValueNormalizer)."""
    value_norm_decay: float = setting(0.99, interval(0, 1, high_open=True))
    """Weight of the old return statistics at each iteration."""

    def __post_init__(self) -> None:
        self.validate()

    def validate(self) -> None:
        """Raises ``ValueError`` naming the first setting of the wrong type or outside its
        range."""
        check_fields(self, "loss")

    def make(self, networks: TerraShiftNetworks, *, max_batch: int) -> Algorithm:
        """The algorithm on ``networks``; its estimation pass runs at most ``max_batch``
        environments' sequences at a time."""
        raise NotImplementedError


@dataclass
class MAPOCAConfig(LossConfig):
    """MA-POCA's loss settings: the shared ones, the baseline's weight and the teacher."""

    algo: ClassVar[str] = "mapoca"
    baseline_coeff: float = setting(0.5, at_least(0))
    """Weight of the counterfactual baseline's loss."""
    teacher_coeff: float = setting(0.0, at_least(0))
    """Weight, at the start, of the pull of the policy's mean action towards the scripted
    heuristic's action (:class:`~terrashift_rl.envs.baselines.ScriptedHeuristicPolicy`, computed
    on every collected step); 0 trains without a teacher."""
    teacher_coeff_end: float = setting(0.0, at_least(0))
    """The teacher's weight after ``teacher_iterations`` updates, held from then on; 0 lets
    the policy learn from the reward alone."""
    teacher_iterations: int = setting(200, at_least(1))
    """Updates over which the teacher's weight falls linearly to ``teacher_coeff_end``."""

    def validate(self) -> None:
        super().validate()
        if self.teacher_coeff_end and not self.teacher_coeff:
            raise ValueError(
                f"loss.teacher_coeff_end is {self.teacher_coeff_end} but loss.teacher_coeff "
                f"is 0 (no teacher): set loss.teacher_coeff > 0 to train with a teacher"
            )

    def make(self, networks: TerraShiftNetworks, *, max_batch: int) -> Algorithm:
        return make_mapoca(networks, self, max_batch=max_batch)


@dataclass
class MAPPOConfig(LossConfig):
    """MAPPO's loss settings: the shared ones; the advantages come from the value, so its weight
    is > 0."""

    algo: ClassVar[str] = "mappo"
    value_coeff: float = setting(1.0, above(0))
    """Weight of the value loss (> 0: the advantages are learned from the value)."""

    def make(self, networks: TerraShiftNetworks, *, max_batch: int) -> Algorithm:
        return make_mappo(networks, self, max_batch=max_batch)


@dataclass
class IPPOConfig(LossConfig):
    """IPPO's loss settings: the shared ones; the advantages come from the per-agent values, so
    their weight is > 0."""

    algo: ClassVar[str] = "ippo"
    value_coeff: float = setting(1.0, above(0))
    """Weight of the value loss (> 0: the advantages are learned from the values)."""

    def make(self, networks: TerraShiftNetworks, *, max_batch: int) -> Algorithm:
        return make_ippo(networks, self, max_batch=max_batch)


@dataclass
class Algorithm:
    """A loss on the shared networks and what the trainer needs to know to run it.

    Attributes:
        loss: maps a mini-batch of whole sequences to ``loss_*`` terms, whose sum is minimised,
            and scalar or per-element diagnostics, among them ``kl_approx`` (the adaptive
            learning rate reads it). Its ``clip_epsilon``, ``entropy_coeff`` and ``clip_value``
            are buffers the schedules assign.
        estimate: the value-estimation pass, run once per collected batch ``[N, T]`` with the
            parameters that collected it; writes returns, old values and advantages into it.
        critics: the modules trained at ``lr_value_baseline`` (the trunk and the policy head
            are trained at ``lr_trunk_policy``).
        critic_terms: the loss terms a critic warm-up step minimises.
        networks: networks of the algorithm that are not part of
            :class:`~terrashift_rl.modules.TerraShiftNetworks` (IPPO's per-agent value head);
            checkpoints hold them beside the shared networks.
        value_normalizer: the running statistics the critics learn normalised returns with, or
            ``None``.
        capturable: whether the loss runs without host synchronisation, so that a mini-batch
            update can be captured as a CUDA graph. torchrl's PPO losses synchronise (a
            truthiness test of ``clip_value``, a finiteness check of the entropy), so their
            updates run eagerly; the actor's collection step is replayed either way.
    """

    loss: LossModule
    estimate: Callable[[TensorDictBase], TensorDictBase]
    critics: list[nn.Module]
    critic_terms: tuple[str, ...]
    networks: nn.ModuleDict
    value_normalizer: ValueNormalizer | None
    capturable: bool


class EmbeddingCriticEstimate:
    """Value-estimation pass of a torchrl PPO loss whose critic reads the trunk's embedding.

    In the loss, the critic is a head on the embedding that the actor has just written, so the
    trunk runs once per mini-batch. Here, without an actor pass, ``value_network`` (trunk +
    critic) runs in torchrl's step mode: every element from the recurrent state stored with it at
    collection, on ``data["next"]`` from the state stored after the step, which reproduces the
    collection's memory exactly (:mod:`terrashift_rl.modules.networks`). V(s_{t+1}) is read
    from step t + 1 within episodes and computed on ``data["next"]`` only where step t ended an
    episode and at the last step, as :class:`~terrashift_rl.objectives.MAPOCAValueEstimator`
    does with ``reuse_root_values``, and as it reads nothing on the host but how many states
    that is. On the batch's own states the critic alone reads the embedding that collection
    stored, as the actor wrote it with the same parameters (``critic``); the trunk runs on
    ``data["next"]`` alone. The networks run on at most as many elements at a time as
    ``max_batch`` rows hold.

    The loss's value estimator (a :class:`~torchrl.objectives.value.MultiAgentGAE` without a
    value network, in its recursive form) then reads these values from the data and writes the
    advantages and returns.
    With a :class:`ValueNormalizer` the critic's outputs are denormalised for the GAE, the
    normaliser is updated with the new returns, and the returns are stored normalised, in the
    critic's units, beside the old values as the critic output them.

    Args:
        loss: a torchrl PPO loss whose value estimator reads precomputed values.
        value_network: trunk + critic, writing the loss's value key.
        critic: the critic alone, reading the embedding.

    Keyword Args:
        max_batch: the networks run on at most as many elements at a time as this many rows of
            the collected batch hold; ``None`` runs them on the whole batch.
        value_normalizer: the critic's running return statistics, or ``None``.
    """

    def __init__(
        self,
        loss: LossModule,
        value_network: TensorDictModule,
        critic: TensorDictModule,
        *,
        max_batch: int | None = None,
        value_normalizer: ValueNormalizer | None = None,
    ) -> None:
        self.loss = loss
        self.value_network = value_network
        self.critic = critic
        self.max_batch = max_batch
        self.value_normalizer = value_normalizer

    @torch.no_grad()
    def __call__(self, data: TensorDictBase) -> TensorDictBase:
        """Writes the old values, returns and advantages into ``data`` ``[N, T]``."""
        value_key = self.loss.tensor_keys.value
        # pieces of at most as many elements as max_batch rows hold
        elements = None if self.max_batch is None else self.max_batch * math.prod(data.shape[1:])
        with set_exploration_type(ExplorationType.DETERMINISTIC), set_recurrent_mode(False):
            value = self._values(self.critic, data.exclude("next"), elements)
            # runs on "next" where step t + 1's root is another episode or outside the batch
            fresh = data.get(("next", "done")).squeeze(-1).clone()
            fresh[..., -1] = True
            next_value = value.roll(-1, dims=data.ndim - 1)
            index = fresh.flatten().nonzero().squeeze(-1)  # the pass's one host read
            fresh_value = self._values(
                self.value_network, data.get("next").reshape(-1)[index], elements
            )
            next_value.flatten(0, data.ndim - 1).index_copy_(0, index, fresh_value)
        stored = value
        normalizer = self.value_normalizer
        if normalizer is not None:
            value, next_value = normalizer.denormalize(value), normalizer.denormalize(next_value)
        data.set(value_key, value)
        data.set(("next", value_key), next_value)
        self.loss.value_estimator(data)
        del data["next", value_key]
        data.set(value_key, stored)  # the old value the value loss is clipped around
        if normalizer is not None:
            value_target = data.get(self.loss.tensor_keys.value_target)
            normalizer.update(value_target)
            data.set(self.loss.tensor_keys.value_target, normalizer.normalize(value_target))
        return data

    def _values(
        self, network: TensorDictModule, tensordict: TensorDictBase, elements: int | None
    ) -> Tensor:
        """``network`` on ``tensordict`` in pieces of whole leading rows that hold at most
        ``elements`` batch elements (at least one row)."""
        key = self.loss.tensor_keys.value
        rows = tensordict.shape[0]
        if elements is not None:
            rows = max(1, elements // math.prod(tensordict.shape[1:]))
        pieces = [network(piece.copy()).get(key) for piece in tensordict.split(rows)]
        return torch.cat(pieces)


class _ToAgents(nn.Module):
    """The team value [..., 1] repeated for each agent of the embedding [..., K, d]."""

    def forward(self, team_value: Tensor, embedding: Tensor) -> Tensor:
        return team_value.unsqueeze(-2).expand(*embedding.shape[:-1], 1)


def _team_value_per_agent() -> TensorDictModule:
    return TensorDictModule(
        _ToAgents(), in_keys=[keys.STATE_VALUE, keys.AGENT_EMBEDDING], out_keys=[AGENT_VALUE]
    )


def _value_normalizer(config: LossConfig, device: torch.device) -> ValueNormalizer | None:
    if not config.normalize_value:
        return None
    synchronize = distributed.world_size() > 1  # one set of return statistics for every rank
    return ValueNormalizer(config.value_norm_decay, synchronize=synchronize).to(device)


def make_mapoca(networks: TerraShiftNetworks, config: MAPOCAConfig, *, max_batch: int) -> Algorithm:
    """MA-POCA: the centralised value for the returns, counterfactual baselines for the
    advantages."""
    device = next(networks.parameters()).device
    normalizer = _value_normalizer(config, device)
    loss = MAPOCALoss(
        networks.actor,
        networks.value_head,
        networks.baseline_head,
        clip_epsilon=config.clip_epsilon_start,
        entropy_coeff=config.entropy_coeff_start,
        value_coeff=config.value_coeff,
        baseline_coeff=config.baseline_coeff,
        clip_value=config.clip_value_start,
        value_normalizer=normalizer,
        teacher_coeff=config.teacher_coeff or None,
    ).to(device)
    loss.make_value_estimator(
        ValueEstimators.GAE,
        gamma=config.gamma,
        lmbda=config.lmbda,
        max_batch=max_batch,
        reuse_root_values=True,  # collected trajectories: next[t] is the root of t + 1
        reuse_actor_outputs=True,  # the embedding collection stored, with these parameters
    )
    return Algorithm(
        loss=loss,
        estimate=loss.value_estimator,
        critics=[networks.value_head, networks.baseline_head],
        critic_terms=("loss_critic", "loss_baseline"),
        networks=nn.ModuleDict(),
        value_normalizer=normalizer,
        capturable=True,
    )


def _make_ppo(
    loss_class: type[MAPPOLoss],
    networks: TerraShiftNetworks,
    config: LossConfig,
    *,
    max_batch: int,
    critic: TensorDictModule,
    critics: list[nn.Module],
    algorithm_networks: nn.ModuleDict,
) -> Algorithm:
    """torchrl's clipped PPO with ``critic`` (a head writing V per agent on the embedding)."""
    device = next(networks.parameters()).device
    normalizer = _value_normalizer(config, device)
    loss = loss_class(
        networks.actor,
        critic,
        clip_epsilon=config.clip_epsilon_start,
        entropy_coeff=config.entropy_coeff_start,
        critic_coeff=config.value_coeff,
        clip_value=config.clip_value_start,
        # standardised once per collected batch by the estimator, as MA-POCA's are
        normalize_advantage=False,
        # the networks hold their parameters, shared with the trainer's optimiser
        functional=False,
    ).to(device)
    # vectorized=False: the recursion over time, where the vectorised form splits the batch at
    # its episode ends and so reads them on the host
    estimator = MultiAgentGAE(
        gamma=config.gamma,
        lmbda=config.lmbda,
        value_network=None,
        average_gae=True,
        vectorized=False,
    )
    loss.make_value_estimator(estimator.to(device))
    # after the estimator, so that it receives the keys too
    loss.set_keys(
        value=AGENT_VALUE,
        value_target=VALUE_TARGET,
        advantage=ADVANTAGE,
        reward=("agents", "reward"),
        done="done",
        terminated="terminated",
    )
    estimate = EmbeddingCriticEstimate(
        loss,
        TensorDictSequential(networks.trunk, critic),
        critic,
        max_batch=max_batch,
        value_normalizer=normalizer,
    )
    return Algorithm(
        loss=loss,
        estimate=estimate,
        critics=critics,
        critic_terms=("loss_critic",),
        networks=algorithm_networks,
        value_normalizer=normalizer,
        capturable=False,
    )


def make_mappo(networks: TerraShiftNetworks, config: MAPPOConfig, *, max_batch: int) -> Algorithm:
    """MAPPO: clipped PPO with the centralised value V(s) as every agent's value."""
    critic = TensorDictSequential(networks.value_head, _team_value_per_agent())
    return _make_ppo(
        MAPPOLoss,
        networks,
        config,
        max_batch=max_batch,
        critic=critic,
        critics=[networks.value_head],
        algorithm_networks=nn.ModuleDict(),
    )


def make_ippo(networks: TerraShiftNetworks, config: IPPOConfig, *, max_batch: int) -> Algorithm:
    """IPPO: clipped PPO with a value per agent on the agent's own embedding."""
    if networks.config is None:
        raise ValueError(
            "algo=ippo sizes its per-agent value head by the networks' config: build the "
            "networks with make_terrashift_networks (or pass config= to TerraShiftNetworks)"
        )
    if networks.config.critic_objects:
        raise ValueError(
            "algo=ippo's value reads each agent's own embedding, not the privileged objects "
            "that model.critic_objects=true gives MA-POCA's and MAPPO's critics: set "
            "model.critic_objects=false and env.privileged_objects=false, or another algo"
        )
    device = next(networks.parameters()).device
    head = make_agent_value_head(networks.config).to(device)
    return _make_ppo(
        IPPOLoss,
        networks,
        config,
        max_batch=max_batch,
        critic=head,
        critics=[head],
        algorithm_networks=nn.ModuleDict({"agent_value_head": head}),
    )


ALGORITHMS: dict[str, type[LossConfig]] = {
    config.algo: config for config in (MAPOCAConfig, MAPPOConfig, IPPOConfig)
}
"""``algo`` -> the algorithm's loss settings, which build it (:meth:`LossConfig.make`)."""
