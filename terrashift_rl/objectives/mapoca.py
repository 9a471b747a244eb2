"""MA-POCA: PPO with a centralised value and per-agent counterfactual baselines.

Cohen et al. 2021, "On the Use and Misuse of Absorbing States in Multi-agent Reinforcement
Learning" (arXiv 2111.05992), as Unity ML-Agents' POCA trainer implements it. A team of K agents
shares one reward. The centralised value V(s) gives the λ-returns G; each agent's counterfactual
baseline b_i(s, a_-i) predicts G with agent i's own action left out, so the advantage
A_i = G - b_i credits agent i for what its own action changed. V and every b_i regress onto G.

Two passes, as with torchrl's PPO losses:

1. The value-estimation pass, ``loss.value_estimator(data)``, once per collected batch with the
   parameters that collected it. It writes the returns, the old value and baselines and the
   per-agent advantages into ``data``.
2. ``loss(minibatch)`` for every mini-batch of every epoch: clipped surrogate, clipped value and
   baseline regressions, entropy bonus.
"""

from __future__ import annotations

import contextlib
import functools
import math
import warnings
from collections.abc import Iterator
from dataclasses import dataclass, fields
from typing import Literal

import torch
from tensordict import TensorDict, TensorDictBase, TensorDictParams
from tensordict.nn import ProbabilisticTensorDictSequential, TensorDictModule
from tensordict.utils import NestedKey
from torch import distributions as d
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.modules import set_recurrent_mode
from torchrl.objectives import LossModule, ValueEstimators, distance_loss
from torchrl.objectives.value.functional import (
    generalized_advantage_estimate,
    td_lambda_return_estimate,
)

from terrashift_rl.objectives.normalization import ValueNormalizer

__all__ = ["AUTO_PIECE_ELEMENTS", "MAPOCALoss", "MAPOCAValueEstimator"]

_ADVANTAGE_STD_EPS = 1e-8
"""Added to the standard deviation when normalising advantages (as ML-Agents does)."""

AUTO_PIECE_ELEMENTS = 1024
"""Batch elements per piece of the value-estimation pass with ``max_batch="auto"``: about a
mini-batch's worth, so that the pass holds about what a mini-batch step holds, however large
the collected batch (docs/benchmarks.md, "Loss speed")."""

_KEY_CONTENTS = {
    "action": "the agents' actions at collection, [*B, K, A] ([*B, K] for discrete actions)",
    "sample_log_prob": (
        "the log-probabilities of the actions at collection, [*B, K] or [*B, K, A] (a torchrl "
        "ProbabilisticActor built with return_log_prob=True writes them)"
    ),
    "reward": "the team reward, [*B, 1], or the agents' rewards, [*B, K, 1]",
    "done": "the done flags (terminated or truncated), [*B, 1] or [*B, K, 1]",
    "terminated": "the terminated flags, [*B, 1] or [*B, K, 1]",
    "value": "the old team values V(s), [*B, 1], that loss.value_estimator(data) writes",
    "baseline": "the old baselines, [*B, K, 1], that loss.value_estimator(data) writes",
    "value_target": "the λ-returns, [*B, 1], that loss.value_estimator(data) writes",
    "advantage": "the advantages, [*B, K, 1], that loss.value_estimator(data) writes",
    "teacher_action": "the teacher's actions, [*B, K, A] (the loss has a teacher_coeff)",
}
"""What each key the loss reads holds, for the errors that name a missing or mis-shaped one."""


class MAPOCAValueEstimator:
    """The value-estimation pass of a :class:`MAPOCALoss`: returns, old estimates, advantages.

    Built by :meth:`MAPOCALoss.make_value_estimator`; call it as ``loss.value_estimator(data)``
    on a collected batch of shape ``[*B, T]`` (time along the dim named ``"time"``, else the
    last one). It runs without gradients, in ``ExplorationType.DETERMINISTIC`` and in torchrl's
    step mode (recurrent networks read the states stored at collection), and writes into
    ``data`` (keys as set on the loss):

    * ``value`` ``[*B, T, 1]``: V(s_t), the old value the value loss is clipped against.
    * ``value_target`` ``[*B, T, 1]``: G_t, the team λ-return from V alone.
    * ``baseline`` ``[*B, T, K, 1]``: b_i(s_t, a_t^-i), the old baselines.
    * ``advantage`` ``[*B, T, K, 1]``: G_t - b_i (G_t - (w b_i + (1 - w) V(s_t)) with the
      loss's ``counterfactual_weight`` w below 1), normalised over present agents and all
      steps if the loss asks for it; zero for absent agents.

    V(s_{t+1}) comes from running the networks on ``data["next"]``, torchrl's convention: a
    recurrent network reads the collected ``("next", <state>)`` there, the state after step t,
    so V(s_{t+1}) sees exactly the memory the policy had. With ``reuse_root_values``, V(s_{t+1})
    is read from step t + 1 wherever step t did not end an episode, and the networks run on
    ``data["next"]`` only at episode ends and the last step: exact for collected trajectories,
    where ``data["next"]`` at step t is the root of step t + 1, and one network pass cheaper.
    With ``reuse_actor_outputs``, critics that read what the actor writes (a shared trunk's
    embedding) read it on the batch's states as collection stored it, and the actor runs on
    ``data["next"]`` alone: exact for a batch collected with the current parameters, as an
    on-policy batch is before its update.

    The networks run in pieces of whole rows of the leading batch dim (``max_batch``): by
    default rows that hold at most :data:`AUTO_PIECE_ELEMENTS` elements, so that the pass's
    memory does not grow with the collected batch; in step mode every element is independent,
    so the pieces give the same values as one pass.

    The pass reads nothing back to the host (on CUDA, every read waits for the device), except,
    with ``reuse_root_values``, how many states follow an episode end: the size of the networks'
    second batch.

    With a :class:`ValueNormalizer` on the loss, the critics' outputs are denormalised for the
    returns and advantages, ``value`` and ``baseline`` are stored as the critics output them,
    ``value_target`` in return units, and the normaliser is updated with the new targets.

    Attributes:
        value_type: ``ValueEstimators.GAE`` or ``ValueEstimators.TDLambda``. They give the
            same returns whenever ``data["next"]`` at step t is the state of step t + 1 within
            an episode, as in collected data: the GAE value target is then the TD(λ) return.
        gamma: discount γ.
        lmbda: λ of the λ-returns.
        max_batch: rows of the leading batch dim per piece of the networks' passes, ``"auto"``
            (rows of at most :data:`AUTO_PIECE_ELEMENTS` elements) or ``None`` (one pass).
        reuse_root_values: whether V(s_{t+1}) is read from step t + 1 within episodes.
        reuse_actor_outputs: whether the critics read the actor's outputs stored in the batch.
    """

    def __init__(
        self,
        loss: MAPOCALoss,
        *,
        value_type: ValueEstimators,
        gamma: float,
        lmbda: float,
        max_batch: int | Literal["auto"] | None = "auto",
        reuse_root_values: bool = False,
        reuse_actor_outputs: bool = False,
    ) -> None:
        if max_batch not in ("auto", None) and (
            isinstance(max_batch, bool) or not isinstance(max_batch, int) or max_batch < 1
        ):
            raise ValueError(
                f"max_batch must be a positive integer, 'auto' or None, got {max_batch!r}"
            )
        self.loss = loss
        self.value_type = value_type
        self.gamma = gamma
        self.lmbda = lmbda
        self.max_batch = max_batch
        self.reuse_root_values = reuse_root_values
        self.reuse_actor_outputs = reuse_actor_outputs

    def __repr__(self) -> str:
        return (
            f"{type(self).__name__}(value_type={self.value_type.name}, gamma={self.gamma}, "
            f"lmbda={self.lmbda}, max_batch={self.max_batch!r})"
        )

    @torch.no_grad()
    def __call__(
        self,
        tensordict: TensorDictBase,
        *,
        params: TensorDictBase | None = None,
        target_params: TensorDictBase | None = None,
    ) -> TensorDictBase:
        """Writes the value, value target, baselines and advantages into ``tensordict``.

        Keyword Args:
            params: the critics' parameters for V(s_t) and the baselines, laid out as
                ``loss.critic_network_params`` (which holds the networks' own, as do
                ``None`` and its ``detach()``), as torchrl's PPO and MAPPO examples pass them.
            target_params: the critics' parameters for V(s_{t+1}), laid out alike;
                ``loss.target_critic_network_params`` and ``None`` are the networks' own.
        """
        loss = self.loss
        keys = loss.tensor_keys
        if tensordict.batch_dims == 0:
            raise ValueError("The value-estimation pass needs a time dimension in the batch.")
        time_dim = _time_dim(tensordict)
        root = tensordict.copy().exclude("next")
        next_step = tensordict.get("next", None)
        if next_step is None:
            raise KeyError(
                "The value-estimation pass reads the step that follows each sample under "
                "'next' (its observations, reward and done flags); the input has no 'next'."
            )
        next_step = next_step.copy()

        # Step mode: every element runs from the recurrent state stored with it at collection
        # (and "next" from the state stored after the step), which reproduces the collection's
        # hidden states exactly, also across episode boundaries.
        elements = self._piece_elements(root)
        with (
            set_exploration_type(ExplorationType.DETERMINISTIC),
            set_recurrent_mode(False),
            loss._critic_parameters(params, "params"),
        ):
            state_value, baseline = self._critics(
                root, with_baseline=True, elements=elements, run_actor=not self._stored(root)
            )
        agent_mask = loss._agent_mask(tensordict, baseline)
        agent_shape = baseline.shape[:-1]
        done = loss._team_flag(tensordict, "done", agent_mask, agent_shape)
        with (
            set_exploration_type(ExplorationType.DETERMINISTIC),
            set_recurrent_mode(False),
            loss._critic_parameters(target_params, "target_params"),
        ):
            if self.reuse_root_values:
                # runs on "next" where step t + 1's root is another episode or outside the batch
                fresh = done.squeeze(-1).clone()
                fresh.select(time_dim, -1).fill_(True)
                next_state_value = state_value.roll(-1, dims=time_dim)
                # the pass's one host read: how many (the indices, unlike a mask, size the rest)
                index = fresh.flatten().nonzero().squeeze(-1)
                fresh_value, _ = self._critics(
                    next_step.reshape(-1)[index], with_baseline=False, elements=elements
                )
                next_state_value.view(-1, 1).index_copy_(0, index, fresh_value)
            else:
                next_state_value, _ = self._critics(
                    next_step, with_baseline=False, elements=elements
                )
        stored_value, stored_baseline = state_value, baseline
        normalizer = loss.value_normalizer
        if normalizer is not None:
            state_value = normalizer.denormalize(state_value)
            next_state_value = normalizer.denormalize(next_state_value)
            baseline = normalizer.denormalize(baseline)

        team_reward = loss._team_reward(tensordict, agent_mask, agent_shape)
        terminated = loss._team_flag(tensordict, "terminated", agent_mask, agent_shape)
        team_reward = team_reward.to(state_value.dtype)

        # the recursions over time, not torchrl's vectorised forms, which split the batch at
        # its episode ends and so read them on the host
        if self.value_type is ValueEstimators.GAE:
            _, value_target = generalized_advantage_estimate(
                self.gamma,
                self.lmbda,
                state_value,
                next_state_value,
                team_reward,
                done,
                terminated,
                time_dim=time_dim,
            )
        else:
            value_target = td_lambda_return_estimate(
                self.gamma,
                self.lmbda,
                next_state_value,
                team_reward,
                done,
                terminated,
                time_dim=time_dim,
            )

        # the advantage's reference: b_i, or a blend with V while the baselines are still
        # fitted worse than V (counterfactual_weight < 1)
        weight = loss.counterfactual_weight
        value = state_value.unsqueeze(-2)
        residual, difference = value_target.unsqueeze(-2) - value, baseline - value
        if loss.least_variance_weight:
            mask = None if agent_mask is None else agent_mask.unsqueeze(-1)
            weight = torch.minimum(weight, _least_variance_weight(residual, difference, mask))
        advantage = residual - weight * difference
        if loss.normalize_advantage:
            advantage = _masked_standardize(advantage, agent_mask)
        if agent_mask is not None:
            advantage = torch.where(agent_mask.unsqueeze(-1), advantage, 0.0)

        if normalizer is not None:
            normalizer.update(value_target)
        tensordict.set(keys.value, stored_value)
        tensordict.set(keys.value_target, value_target)
        tensordict.set(keys.baseline, stored_baseline)
        tensordict.set(keys.advantage, advantage)
        return tensordict

    def _piece_elements(self, tensordict: TensorDictBase) -> int | None:
        """How many elements of ``tensordict`` a piece of the networks' passes holds at most
        (``None``: all)."""
        if self.max_batch == "auto":
            return AUTO_PIECE_ELEMENTS
        if self.max_batch is None:
            return None
        return self.max_batch * math.prod(tensordict.batch_size[1:])

    def _stored(self, root: TensorDictBase) -> bool:
        """Whether the critics read the actor's outputs from ``root`` as stored
        (``reuse_actor_outputs``); refuses a batch that lacks them."""
        read = self.loss._actor_outputs_read
        if not (self.reuse_actor_outputs and read):
            return False
        missing = [key for key in read if key not in root.keys(True)]
        if missing:
            raise KeyError(
                f"reuse_actor_outputs: the batch lacks {missing}, which the critics read from "
                "the actor; keep the actor's outputs in the batch or set it False."
            )
        return True

    def _critics(
        self,
        tensordict: TensorDictBase,
        *,
        with_baseline: bool,
        elements: int | None,
        run_actor: bool = True,
    ) -> tuple[torch.Tensor, torch.Tensor | None]:
        """The loss's critics (after the actor if ``run_actor``) on ``tensordict``, in pieces of
        whole leading rows that hold at most ``elements`` batch elements (at least one row; in
        step mode every element is independent, so the pieces give the same values)."""
        rows = None if elements is None else max(1, elements // math.prod(tensordict.shape[1:]))
        run = functools.partial(
            self.loss._run_critics, with_baseline=with_baseline, run_actor=run_actor
        )
        if rows is None or tensordict.shape[0] <= rows:
            return run(tensordict)
        pieces = [run(piece) for piece in tensordict.split(rows, dim=0)]
        value = torch.cat([value for value, _ in pieces])
        baseline = torch.cat([b for _, b in pieces]) if with_baseline else None
        return value, baseline


class MAPOCALoss(LossModule):
    """MA-POCA loss: PPO with a centralised value V(s) and counterfactual baselines b_i.

    The networks are three TensorDict modules that may share a trunk (the same ``nn.Module``
    inside each): the loss counts shared parameters once and every term backpropagates into
    them. On any tensordict the loss runs the actor's parameter module first, then the value
    network, then the baseline network, so heads may read what the actor writes (say, the
    per-agent embedding of a shared trunk): the trunk then runs once per pass. Self-contained
    value and baseline networks work too: :class:`~terrashift_rl.modules.CentralValue` and
    :class:`~terrashift_rl.modules.CounterfactualBaseline` are such networks for any team with
    flat per-agent observations, and the loss's default keys are those of torchrl's VMAS
    environments.

    Per mini-batch, with ρ_i = π(a_i | s) / π_old(a_i | s) per agent (joint over the action
    dims unless ``per_dimension_ratio``), ε the clip range, and masked means over present
    agents and samples:

    * ``loss_objective = -mean(min(ρ_i A_i, clip(ρ_i, 1 - ε, 1 + ε) A_i))``, the log-ratio
      clamped to ``±max_log_ratio`` first;
    * ``loss_critic = value_coeff * mean(d(V, G))``, ``d`` the squared or Huber distance,
      ``max(d(V, G), d(V_old + clip(V - V_old, ±clip_value), G))`` when clipped;
    * ``loss_baseline = baseline_coeff * mean(d(b_i, G))``, clipped against b_old alike;
    * ``loss_entropy = -entropy_coeff * mean(H_i)``, H_i summed over action dims;
    * with ``teacher_coeff``, ``loss_teacher = teacher_coeff * mean(|E[π(· | s)] - a*_i|²)``,
      the squared distance (summed over action dims) from the policy's mean action to a
      teacher's action a*_i read at the ``teacher_action`` key: a pull towards a demonstrator
      (a scripted controller, an older policy) that a schedule can fade out.

    The loss to minimise is the sum of every ``loss_*`` term of the output, as torchrl's
    trainers add them up: ``sum(v for k, v in losses.items() if k.startswith("loss_"))``. A
    MAPPO loop adds ``loss_objective + loss_critic + loss_entropy`` by name instead; with this
    loss it would leave out ``loss_baseline``, and the baselines, from which every advantage
    comes, would never train. The loss therefore warns, once, when a backward pass has gone
    through ``loss_critic`` but not ``loss_baseline``.

    Returns come from V alone on the team reward: termination stops the bootstrap,
    truncation (and the end of the batch) bootstraps from V(s_{t+1}), and done (terminated or
    truncated) stops the λ-recursion.

    The team reward and the done flags may sit at the root (``[*B, 1]``) or in the group
    (``[*B, K, 1]``), told apart by shape. A per-agent reward is reduced over the agents present
    at the step (``team_reward_reduction``); per-agent flags are true for the team when true for
    every present agent. Absent agents (``mask`` False) drop out of every mean, of the reward
    and of the advantage normalisation; their action, log-prob and observation entries must
    still be finite. The networks must keep them out of the attention sets themselves.

    The coefficients and clip ranges (``clip_value`` and ``teacher_coeff`` when not ``None``)
    are float buffers that torchrl's ``LossModule`` lets a schedule assign in place:
    ``loss.entropy_coeff = 0.001`` keeps device and dtype.

    The loss runs its networks with the parameters they hold (they are plain submodules, so
    that a trunk they share trains through every term), and exposes the critics' parameters as
    torchrl's PPO losses do: :attr:`critic_network_params`, a ``TensorDictParams`` of the value
    and baseline networks' parameters, and :attr:`target_critic_network_params`, their detached
    data. The call of torchrl's PPO examples, ``loss.value_estimator(data,
    params=loss.critic_network_params, target_params=loss.target_critic_network_params)``,
    works, with ``params=loss.critic_network_params.detach()`` too, and other parameters of the
    same layout run the estimation pass with them. :attr:`in_keys` lists the keys the two
    passes require, and an input that is missing or of the wrong shape raises an error naming
    its key and the shape expected.

    The defaults are :class:`~torchrl.objectives.ClipPPOLoss`'s (``clip_epsilon=0.2``,
    ``entropy_coeff=0.01``, ``value_coeff`` as its ``critic_coeff=1.0``, a smooth-L1 critic
    loss, no value clipping) but for three:

    * ``normalize_advantage=True``, as torchrl's multi-agent
      :class:`~torchrl.objectives.multiagent.MAPPOLoss` and the MAPPO paper (Yu et al. 2022):
      A_i = G - b_i carries the reward's scale, which differs by orders of magnitude between
      tasks, while the clip range and the entropy coefficient suppose advantages of about
      unit scale. The advantages are standardised once per collected batch, over every agent
      and step (ClipPPOLoss does it per mini-batch).
    * ``baseline_coeff=0.5``, a weight ClipPPOLoss has no counterpart of: ML-Agents' POCA
      weighs the baseline regression half the value regression (its critic term is
      0.5 (L_V + 0.5 L_b)).
    * ``max_log_ratio=8.0``, a guard ClipPPOLoss does not have: exp of a log-ratio beyond 11
      overflows float16 and beyond 88 float32, and one infinite ratio makes every gradient
      NaN. e^8 ≈ 3000 lies far beyond the ratios that clipped updates reach, so healthy
      training never meets the clamp.

    Args:
        actor_network: the group's policy, e.g. a torchrl ``ProbabilisticActor`` writing the
            ``action`` key [*B, K, A] and its log-prob ([*B, K] joint or [*B, K, A] per dim).
        value_network: writes the team value at the ``value`` key, [*B, 1].
        baseline_network: reads the group's embeddings or observations and actions, writes the
            ``baseline`` key, [*B, K, 1].

    Keyword Args:
        clip_epsilon: PPO clip range ε of the ratio.
        entropy_coeff: weight of the entropy bonus.
        value_coeff: weight of the value loss.
        baseline_coeff: weight of the baseline loss.
        clip_value: clip range of V and b around their old estimates; ``None`` does not clip.
        loss_critic_type: ``"l2"`` (squared error), ``"smooth_l1"`` (Huber) or ``"l1"``.
        normalize_advantage: standardise the advantages over present agents and all steps in
            the value-estimation pass (once per collected batch).
        per_dimension_ratio: one ratio per action dimension, averaged in the surrogate
            (ML-Agents); needs per-dimension log-probs. The default is the joint per-agent ratio
            of the paper's Eq. 8.
        max_log_ratio: clamp of the log-ratio before exponentiation; ``None`` disables it.
        team_reward_reduction: how a per-agent reward becomes the team reward: ``"mean"`` over
            present agents (right when every agent carries a copy of the team reward, as in
            TerraShift) or ``"sum"`` (individual rewards, as ML-Agents adds them up).
        value_normalizer: a :class:`ValueNormalizer`: the value and baseline networks then
            learn normalised returns (the estimator keeps its statistics); ``None`` trains them
            on raw returns.
        teacher_coeff: weight of the pull of the policy's mean action towards the
            ``teacher_action`` key (the policy's distribution must have a ``mean``); ``None``
            reads no teacher.
        counterfactual_weight: w in A_i = G - (w b_i + (1 - w) V), in [0, 1]. 1 is MA-POCA's
            counterfactual advantage; 0 the centralised value's G - V, MAPPO's (the baselines
            still train). Early in training the baselines, which also read the other agents'
            actions, fit the returns worse than V, and their error is noise in every agent's
            advantage: a schedule from 0 to 1 over the first updates starts as fast as MAPPO
            and ends with the counterfactual credit (docs/results.md, "MAPOCALoss on VMAS").
        least_variance_weight: in each value-estimation pass, lower w to the blend whose
            advantages vary least over the batch, Cov(G - V, b_i - V) / Var(b_i - V) clipped to
            [0, 1], where that is below ``counterfactual_weight``: the baselines weigh in as
            far as they take noise out of the advantages.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from tensordict.nn import TensorDictModule
        >>> from torch import nn
        >>> from torchrl.envs.utils import ExplorationType, set_exploration_type
        >>> from torchrl.modules import IndependentNormal, NormalParamExtractor, ProbabilisticActor
        >>> from torchrl.objectives import ValueEstimators
        >>> from terrashift_rl.modules import CentralValue, CounterfactualBaseline
        >>> from terrashift_rl.objectives import MAPOCALoss
        >>> _ = torch.manual_seed(0)
        >>> n_envs, n_steps, n_agents, obs_dim, action_dim = 2, 5, 3, 4, 2
        >>> actor = ProbabilisticActor(
        ...     TensorDictModule(
        ...         nn.Sequential(nn.Linear(obs_dim, 2 * action_dim), NormalParamExtractor()),
        ...         in_keys=[("agents", "observation")],
        ...         out_keys=[("agents", "loc"), ("agents", "scale")]),
        ...     in_keys=[("agents", "loc"), ("agents", "scale")],
        ...     out_keys=[("agents", "action")], distribution_class=IndependentNormal,
        ...     return_log_prob=True)
        >>> value = CentralValue(obs_dim, width=16, num_heads=2)
        >>> baseline = CounterfactualBaseline(obs_dim, action_dim, width=16, num_heads=2)
        >>> loss = MAPOCALoss(actor, value, baseline, clip_value=0.2)
        >>> loss = loss.make_value_estimator(ValueEstimators.GAE, gamma=0.95, lmbda=0.92)
        >>> batch = [n_envs, n_steps]
        >>> data = TensorDict({
        ...     ("agents", "observation"): torch.randn(*batch, n_agents, obs_dim),
        ...     ("next", "agents", "observation"): torch.randn(*batch, n_agents, obs_dim),
        ...     ("next", "agents", "reward"): torch.randn(*batch, n_agents, 1),
        ...     ("next", "done"): torch.zeros(*batch, 1, dtype=torch.bool),
        ...     ("next", "terminated"): torch.zeros(*batch, 1, dtype=torch.bool),
        ... }, batch_size=batch)
        >>> with torch.no_grad(), set_exploration_type(ExplorationType.RANDOM):
        ...     data = actor(data)  # collection: samples actions, stores their log-probs
        >>> data = loss.value_estimator(  # as torchrl's PPO examples call it
        ...     data, params=loss.critic_network_params,
        ...     target_params=loss.target_critic_network_params)
        >>> data["agents", "advantage"].shape, data["value_target"].shape
        (torch.Size([2, 5, 3, 1]), torch.Size([2, 5, 1]))
        >>> for minibatch in data.reshape(-1).split(5):
        ...     losses = loss(minibatch)
        ...     total = sum(v for k, v in losses.items() if k.startswith("loss_"))
        ...     total.backward()
        >>> sorted(losses.keys())  # doctest: +NORMALIZE_WHITESPACE
        ['ESS', 'baseline_clip_fraction', 'clip_fraction', 'entropy', 'explained_variance',
         'explained_variance_baseline', 'kl_approx', 'loss_baseline', 'loss_critic',
         'loss_entropy', 'loss_objective', 'value_clip_fraction']
        >>> loss.entropy_coeff = 0.001  # a schedule sets coefficients in place
    """

    @dataclass
    class _AcceptedKeys:
        """Tensordict keys the loss reads and writes; change them with ``set_keys``.

        ``set_keys(group="team")`` moves every key that lives in the current group (first
        element equal to ``group``) into the new one; keys passed in the same call win.

        Attributes:
            group: the agents' group, whose tensordict has batch shape [*B, K].
            action: per-agent action [*B, K, A] (or [*B, K] for discrete actions).
            sample_log_prob: log-prob of ``action`` at collection, [*B, K] or [*B, K, A].
            mask: bool [*B, K] (or [*B, K, 1]), True where the agent is present. Optional:
                absent means every agent is present.
            reward: read under ``"next"``; the team reward [*B, 1] or per-agent [*B, K, 1].
            done: read under ``"next"``; terminated or truncated, [*B, 1] or [*B, K, 1].
            terminated: read under ``"next"``; [*B, 1] or [*B, K, 1]. Truncation is
                ``done & ~terminated``, so no truncated key is read.
            value: team value V [*B, 1], written by the value network and, as the old value,
                by the value-estimation pass.
            baseline: per-agent baselines [*B, K, 1], written by the baseline network and, as
                the old baselines, by the value-estimation pass.
            value_target: the λ-return G [*B, 1], written by the value-estimation pass.
            advantage: G - b_i [*B, K, 1], written by the value-estimation pass.
            teacher_action: a teacher's action [*B, K, A], read with ``teacher_coeff`` only.
        """

        group: str = "agents"
        action: NestedKey = ("agents", "action")
        sample_log_prob: NestedKey = ("agents", "action_log_prob")
        mask: NestedKey = ("agents", "mask")
        reward: NestedKey = ("agents", "reward")
        done: NestedKey = "done"
        terminated: NestedKey = "terminated"
        value: NestedKey = "state_value"
        baseline: NestedKey = ("agents", "baseline")
        value_target: NestedKey = "value_target"
        advantage: NestedKey = ("agents", "advantage")
        teacher_action: NestedKey = ("agents", "teacher_action")

    default_keys = _AcceptedKeys
    tensor_keys: _AcceptedKeys
    default_value_estimator = ValueEstimators.GAE
    SUPPORTED_VALUE_ESTIMATORS = (ValueEstimators.GAE, ValueEstimators.TDLambda)
    _schedulable_buffers = frozenset(
        {
            "clip_epsilon",
            "entropy_coeff",
            "value_coeff",
            "baseline_coeff",
            "clip_value",
            "teacher_coeff",
            "counterfactual_weight",
        }
    )

    actor_network: ProbabilisticTensorDictSequential
    value_network: TensorDictModule
    baseline_network: TensorDictModule

    def __init__(
        self,
        actor_network: ProbabilisticTensorDictSequential,
        value_network: TensorDictModule,
        baseline_network: TensorDictModule,
        *,
        clip_epsilon: float = 0.2,
        entropy_coeff: float = 0.01,
        value_coeff: float = 1.0,
        baseline_coeff: float = 0.5,
        clip_value: float | None = None,
        loss_critic_type: Literal["l2", "smooth_l1", "l1"] = "smooth_l1",
        normalize_advantage: bool = True,
        per_dimension_ratio: bool = False,
        max_log_ratio: float | None = 8.0,
        team_reward_reduction: Literal["mean", "sum"] = "mean",
        value_normalizer: ValueNormalizer | None = None,
        teacher_coeff: float | None = None,
        counterfactual_weight: float = 1.0,
        least_variance_weight: bool = False,
    ) -> None:
        if team_reward_reduction not in ("mean", "sum"):
            raise ValueError(
                f"team_reward_reduction must be 'mean' or 'sum', got {team_reward_reduction!r}."
            )
        if loss_critic_type not in ("l2", "smooth_l1", "l1"):
            raise ValueError(
                f"loss_critic_type must be 'l2', 'smooth_l1' or 'l1', got {loss_critic_type!r}."
            )
        if isinstance(counterfactual_weight, bool) or not 0.0 <= counterfactual_weight <= 1.0:
            raise ValueError(
                f"counterfactual_weight must be a float in [0, 1], got {counterfactual_weight!r}."
            )
        super().__init__()
        # Plain submodules, not torchrl's functional parameter copies: nn.Module then yields a
        # trunk shared by the three networks once, and it trains through all of them.
        self.actor_network = actor_network
        self.value_network = value_network
        self.baseline_network = baseline_network
        device = next(self.parameters()).device
        # float buffers: a schedule assigns fractions even to a coefficient built from an int
        for name, value in (
            ("clip_epsilon", clip_epsilon),
            ("entropy_coeff", entropy_coeff),
            ("value_coeff", value_coeff),
            ("baseline_coeff", baseline_coeff),
            ("clip_value", clip_value),
            ("teacher_coeff", teacher_coeff),
            ("counterfactual_weight", counterfactual_weight),
        ):
            self.register_coeff_buffer(name, value, device=device, dtype=torch.float32)
        self.loss_critic_type = loss_critic_type
        self.normalize_advantage = normalize_advantage
        self.least_variance_weight = least_variance_weight
        self.per_dimension_ratio = per_dimension_ratio
        self.max_log_ratio = max_log_ratio
        self.team_reward_reduction = team_reward_reduction
        self.value_normalizer = value_normalizer
        # what the critics read of the actor's outputs (a shared trunk's embedding)
        self._actor_outputs_read = (
            set(value_network.in_keys) | set(baseline_network.in_keys)
        ) & set(actor_network.det_part.out_keys)
        self._in_keys = None
        # what the last backward pass went through (see _warn_if_baseline_left_out)
        self._backward_reached: dict[str, bool] | None = None
        self._warned_baseline_left_out = False
        log_prob_keys = actor_network.log_prob_keys
        action_keys = actor_network.dist_sample_keys
        if len(log_prob_keys) == 1 and len(action_keys) == 1:
            self.set_keys(sample_log_prob=log_prob_keys[0], action=action_keys[0])

    @property
    def functional(self) -> bool:
        return False

    @property
    def critic_network_params(self) -> TensorDictParams:
        """The value and baseline networks' parameters and buffers (the tensors themselves, not
        copies), under ``"value_network"`` and ``"baseline_network"``: what torchrl's PPO
        losses hold as ``critic_network_params``. Not registered as a submodule: the networks
        are, and the state dict holds their tensors once."""
        return TensorDictParams(
            TensorDict({name: TensorDict.from_module(getattr(self, name)) for name in _CRITICS}),
            no_convert=True,
        )

    @property
    def target_critic_network_params(self) -> TensorDictBase:
        """:attr:`critic_network_params`' data, detached: as in torchrl's PPO losses, which have
        no target critic, the same values."""
        return self.critic_network_params.data

    @contextlib.contextmanager
    def _critic_parameters(self, params: TensorDictBase | None, name: str) -> Iterator[None]:
        """A context in which the value and baseline networks run with ``params`` (laid out as
        :attr:`critic_network_params`); with ``None``, with their own."""
        if params is None:
            yield
            return
        if not isinstance(params, TensorDictBase) or set(params.keys()) != set(_CRITICS):
            keys = list(params.keys()) if isinstance(params, TensorDictBase) else type(params)
            raise ValueError(
                f"{name} must be laid out as loss.critic_network_params, a TensorDict with the "
                f"entries {list(_CRITICS)}, got {keys}."
            )
        with (
            params["value_network"].to_module(self.value_network),
            params["baseline_network"].to_module(self.baseline_network),
        ):
            yield

    def set_keys(self, **kwargs: NestedKey | None) -> None:
        """Sets tensordict keys; ``group`` moves the keys that live in the current group.

        ``loss.set_keys(group="team")`` turns ``("agents", "action")`` into ``("team", "action")``
        and likewise for every key under the old group, unless the same call sets it explicitly.
        A value of ``None`` restores the default.
        """
        if "group" in kwargs:
            new_group = kwargs["group"] or self.default_keys.group
            old_group = self.tensor_keys.group
            moved = {
                field.name: (new_group, *key[1:])
                for field in fields(self.tensor_keys)
                if isinstance(key := getattr(self.tensor_keys, field.name), tuple)
                and key[0] == old_group
            }
            kwargs = {**moved, **kwargs, "group": new_group}
        super().set_keys(**kwargs)

    def _forward_value_estimator_keys(self, **kwargs) -> None:
        # The estimator reads the keys from the loss itself: only the in_keys need refreshing.
        self._in_keys = None

    @property
    def in_keys(self) -> list[NestedKey]:
        """The input keys the loss requires (the estimator's included).

        Not listed: what the actor writes, and the optional agent mask (data without one
        means every agent is present). Where the data has a mask, keep it with these keys:
        ``data.select(*loss.in_keys, loss.tensor_keys.mask)``.
        """
        if self._in_keys is None:
            keys = self.tensor_keys
            written = set(self.actor_network.det_part.out_keys)
            value_inputs = [*self.value_network.in_keys]
            if self._actor_outputs_read:
                value_inputs += self.actor_network.in_keys
            value_inputs = [key for key in value_inputs if key not in written]
            network_inputs = [
                *self.actor_network.in_keys,
                *value_inputs,
                *(key for key in self.baseline_network.in_keys if key not in written),
            ]
            in_keys = [*network_inputs, keys.action, keys.sample_log_prob]
            if self.teacher_coeff is not None:
                in_keys.append(keys.teacher_action)
            in_keys += [("next", *_as_tuple(key)) for key in value_inputs]
            in_keys += [
                ("next", *_as_tuple(key)) for key in (keys.reward, keys.done, keys.terminated)
            ]
            optional = {_flatten_key(keys.mask), ("next", *_as_tuple(keys.mask))}
            in_keys = [_flatten_key(key) for key in in_keys]
            self._in_keys = list(dict.fromkeys(key for key in in_keys if key not in optional))
        return self._in_keys

    @in_keys.setter
    def in_keys(self, values: list[NestedKey]) -> None:
        self._in_keys = values

    @property
    def out_keys(self) -> list[str]:
        """Keys of the TensorDict that ``forward`` returns."""
        keys = [
            "loss_objective",
            "loss_critic",
            "loss_baseline",
            "loss_entropy",
            "entropy",
            "clip_fraction",
            "kl_approx",
            "ESS",
            "explained_variance",
            "explained_variance_baseline",
        ]
        if self.clip_value is not None:
            keys += ["value_clip_fraction", "baseline_clip_fraction"]
        if self.teacher_coeff is not None:
            keys += ["loss_teacher", "teacher_distance"]
        return keys

    def make_value_estimator(
        self,
        value_type: ValueEstimators | None = None,
        *,
        gamma: float = 0.99,
        lmbda: float = 0.95,
        max_batch: int | Literal["auto"] | None = "auto",
        reuse_root_values: bool = False,
        reuse_actor_outputs: bool = False,
    ) -> MAPOCALoss:
        """Sets the value-estimation pass, reachable as ``loss.value_estimator``.

        Args:
            value_type: ``ValueEstimators.GAE`` (the default) or ``ValueEstimators.TDLambda``.

        Keyword Args:
            gamma: discount γ.
            lmbda: λ of the λ-returns.
            max_batch: run the networks on at most as many elements at a time as this many
                rows of the leading batch dim hold (bounds memory; the results are the same);
                ``"auto"`` (the default) on rows that hold at most :data:`AUTO_PIECE_ELEMENTS`
                elements (at least one row), about a mini-batch's worth; ``None`` at once.
            reuse_root_values: read V(s_{t+1}) from step t + 1 within episodes and run the
                networks on ``"next"`` only at episode ends and the last step; exact for
                collected trajectories (see :class:`MAPOCAValueEstimator`).
            reuse_actor_outputs: critics that read the actor's outputs (a shared trunk's
                embedding) read them on the batch's states as collection stored them, one
                actor pass fewer; exact for a batch collected with the current parameters.

        Returns:
            The loss, for chaining.
        """
        value_type = self.default_value_estimator if value_type is None else value_type
        if value_type not in self.SUPPORTED_VALUE_ESTIMATORS:
            supported = [estimator.name for estimator in self.SUPPORTED_VALUE_ESTIMATORS]
            raise NotImplementedError(
                f"{type(self).__name__} supports the value estimators {supported}, "
                f"got {value_type!r}."
            )
        self.value_type = value_type
        self._value_estimator = MAPOCAValueEstimator(
            self,
            value_type=value_type,
            gamma=gamma,
            lmbda=lmbda,
            max_batch=max_batch,
            reuse_root_values=reuse_root_values,
            reuse_actor_outputs=reuse_actor_outputs,
        )
        return self

    def _default_value_estimator(self) -> None:
        self.make_value_estimator()

    def forward(self, tensordict: TensorDictBase) -> TensorDict:
        """Computes the MA-POCA loss terms and detached diagnostics on a (mini-)batch.

        Runs the value-estimation pass first if ``tensordict`` has no advantage yet (it then
        uses the current parameters as the old ones, fine for a single epoch).

        Args:
            tensordict: samples with the keys of :attr:`in_keys` and those written by the
                value-estimation pass; any batch shape.

        Returns:
            A TensorDict of scalars: ``loss_objective``, ``loss_critic``, ``loss_baseline``,
            ``loss_entropy`` (the ``loss_*`` terms sum to the loss to minimise) and the diagnostics
            ``entropy``, ``clip_fraction``, ``kl_approx``, ``ESS``, ``explained_variance``,
            ``explained_variance_baseline``; with ``clip_value`` also ``value_clip_fraction``
            and ``baseline_clip_fraction``, with ``teacher_coeff`` ``loss_teacher`` and
            ``teacher_distance`` (the mean squared distance to the teacher's action).
        """
        keys = self.tensor_keys
        self._warn_if_baseline_left_out()
        tensordict = tensordict.copy()
        if keys.advantage not in tensordict.keys(include_nested=True):
            self.value_estimator(tensordict)
        old_log_prob = self._read(tensordict, "sample_log_prob")
        action = self._read(tensordict, "action")
        if old_log_prob.requires_grad or action.requires_grad:
            raise RuntimeError("The stored action and log-prob must not require gradients.")
        # read before the networks run: they write the new value and baselines at these keys
        stored = {
            name: self._read(tensordict, name)
            for name in ("advantage", "value_target", "value", "baseline")
        }

        dist = self.actor_network.get_dist(tensordict)
        value, baseline = self._run_critics(tensordict, with_baseline=True, run_actor=False)
        agent_shape = baseline.shape[:-1]
        team_shape = (*tensordict.batch_size, 1)
        for name, shape in (
            ("advantage", (*agent_shape, 1)),
            ("value_target", team_shape),
            ("value", team_shape),
            ("baseline", (*agent_shape, 1)),
        ):
            self._check_shape(stored[name], name, shape)
        advantage = stored["advantage"].squeeze(-1)
        value_target, old_value, old_baseline = (
            stored[name] for name in ("value_target", "value", "baseline")
        )
        agent_mask = self._agent_mask(tensordict, baseline)

        if action.shape[: len(agent_shape)] != agent_shape or action.ndim > len(agent_shape) + 1:
            raise ValueError(
                f"MAPOCALoss reads {_flatten_key(keys.action)!r} as [*B, K, A] (or [*B, K]) with "
                f"[*B, K] = {list(agent_shape)}, got {list(action.shape)}."
            )
        log_prob = dist.log_prob(action)
        joint_log_prob = _per_agent(log_prob, agent_shape, "the policy's log-prob")
        joint_old_log_prob = _per_agent(
            old_log_prob, agent_shape, f"stored log-prob {_flatten_key(keys.sample_log_prob)!r}"
        )
        if self.per_dimension_ratio:
            if log_prob.shape == agent_shape or old_log_prob.shape == agent_shape:
                raise ValueError(
                    "per_dimension_ratio needs per-dimension log-probs [*B, K, A]; the policy "
                    f"gives {tuple(log_prob.shape)} and the data {tuple(old_log_prob.shape)}."
                )
            log_ratio = log_prob - old_log_prob
            ratio_mask = None if agent_mask is None else agent_mask.unsqueeze(-1)
            ratio_advantage = advantage.unsqueeze(-1)
        else:
            log_ratio = joint_log_prob - joint_old_log_prob
            ratio_mask = agent_mask
            ratio_advantage = advantage
        if self.max_log_ratio is not None:
            log_ratio = log_ratio.clamp(-self.max_log_ratio, self.max_log_ratio)
        ratio = log_ratio.exp()
        clipped_ratio = ratio.clamp(1.0 - self.clip_epsilon, 1.0 + self.clip_epsilon)
        surrogate = torch.minimum(ratio * ratio_advantage, clipped_ratio * ratio_advantage)
        if self.per_dimension_ratio:
            surrogate = surrogate.mean(-1)
        loss_objective = -_masked_mean(surrogate, agent_mask)

        entropy = _masked_mean(_per_agent(_entropy(dist), agent_shape, "entropy"), agent_mask)

        if self.value_normalizer is not None:
            value_target = self.value_normalizer.normalize(value_target)
        loss_critic, value_clip_fraction = self._regression_loss(
            value, old_value, value_target, mask=None
        )
        loss_baseline, baseline_clip_fraction = self._regression_loss(
            baseline.squeeze(-1),
            old_baseline.squeeze(-1),
            value_target.expand_as(advantage),
            mask=agent_mask,
        )

        loss_critic = self.value_coeff * loss_critic
        loss_baseline = self.baseline_coeff * loss_baseline
        out = TensorDict(
            {
                "loss_objective": loss_objective,
                "loss_critic": loss_critic,
                "loss_baseline": loss_baseline,
                "loss_entropy": -self.entropy_coeff * entropy,
            }
        )
        if self.teacher_coeff is not None:
            teacher = self._read(tensordict, "teacher_action")
            self._check_shape(teacher, "teacher_action", dist.mean.shape)
            distance = (dist.mean - teacher).pow(2).sum(-1)
            teacher_distance = _masked_mean(distance, agent_mask)
            out.set("loss_teacher", self.teacher_coeff * teacher_distance)
            out.set("teacher_distance", teacher_distance.detach())
        with torch.no_grad():
            joint_log_ratio = joint_log_prob - joint_old_log_prob
            if self.max_log_ratio is not None:
                joint_log_ratio = joint_log_ratio.clamp(-self.max_log_ratio, self.max_log_ratio)
            out.set("entropy", entropy.detach())
            out.set(
                "clip_fraction",
                _masked_mean(((ratio - 1.0).abs() > self.clip_epsilon).to(ratio.dtype), ratio_mask),
            )
            # Schulman's k3 estimator of KL(pi_old || pi): unbiased, non-negative per sample.
            out.set(
                "kl_approx",
                _masked_mean(joint_log_ratio.exp() - 1.0 - joint_log_ratio, agent_mask),
            )
            out.set("ESS", _effective_sample_fraction(joint_log_ratio, agent_mask))
            out.set("explained_variance", _explained_variance(value_target, value, None))
            out.set(
                "explained_variance_baseline",
                _explained_variance(
                    value_target.expand_as(advantage), baseline.squeeze(-1), agent_mask
                ),
            )
            if value_clip_fraction is not None:
                out.set("value_clip_fraction", value_clip_fraction)
                out.set("baseline_clip_fraction", baseline_clip_fraction)
        self._watch_backward(out)
        return out

    def _run_critics(
        self, tensordict: TensorDictBase, *, with_baseline: bool, run_actor: bool = True
    ) -> tuple[torch.Tensor, torch.Tensor | None]:
        """V [*B, 1] and, if asked, b [*B, K, 1] on ``tensordict``, which receives the outputs."""
        if run_actor and self._actor_outputs_read:
            self.actor_network.get_dist_params(tensordict)
        keys = self.tensor_keys
        team_shape = [*tensordict.batch_size, 1]
        value = self.value_network(tensordict).get(keys.value, None)
        if value is None:
            raise KeyError(
                f"The value network wrote no {_flatten_key(keys.value)!r}, where MAPOCALoss reads "
                f"the team value V(s), [*B, 1] = {team_shape}; it writes "
                f"{self.value_network.out_keys}. Point the loss at its output with "
                "loss.set_keys(value=<key>); a value per agent, [*B, K, 1], as MAPPO's critics "
                "write, must first be pooled over the agents (terrashift_rl.modules.CentralValue "
                "pools them)."
            )
        if list(value.shape) == team_shape:
            pass
        elif value.shape[:-2] == tensordict.batch_size and value.shape[-1:] == (1,):
            raise ValueError(
                f"The value network writes {_flatten_key(keys.value)!r} per agent, "
                f"{list(value.shape)} = [*B, K, 1], as MAPPO's critics do. MAPOCALoss needs one "
                f"team value V(s) per sample, [*B, 1] = {team_shape} (the counterfactual "
                "baselines are its per-agent estimates): pool the agents in the value network, "
                "as terrashift_rl.modules.CentralValue does, or average its output over the "
                "agents (dim -2) in a module after it and point loss.set_keys(value=...) there."
            )
        else:
            raise ValueError(
                f"The value network must write {_flatten_key(keys.value)!r} with shape [*B, 1] "
                f"= {team_shape}, got {list(value.shape)}."
            )
        if not with_baseline:
            return value, None
        baseline = self.baseline_network(tensordict).get(keys.baseline, None)
        if baseline is None:
            raise KeyError(
                f"The baseline network wrote no {_flatten_key(keys.baseline)!r}, where "
                "MAPOCALoss reads the counterfactual baselines, [*B, K, 1]; it writes "
                f"{self.baseline_network.out_keys}. Point the loss at its output with "
                "loss.set_keys(baseline=<key>)."
            )
        if baseline.shape[:-2] != tensordict.batch_size or baseline.shape[-1:] != (1,):
            raise ValueError(
                f"The baseline network must write {_flatten_key(keys.baseline)!r} with shape "
                f"[*B, K, 1], [*B] = {list(tensordict.batch_size)}, got {list(baseline.shape)}."
            )
        return value, baseline

    def _read(
        self, tensordict: TensorDictBase, name: str, *, step: Literal["root", "next"] = "root"
    ) -> torch.Tensor:
        """The entry at the key ``name`` (under ``"next"`` for ``step="next"``); an error that
        names the key and what it should hold if it is missing."""
        key = getattr(self.tensor_keys, name)
        if step == "next":
            key = _flatten_key(("next", *_as_tuple(key)))
        value = tensordict.get(key, None)
        if value is None:
            raise KeyError(
                f"MAPOCALoss reads {key!r}, {_KEY_CONTENTS[name]}; the input has no such key. "
                f"If the data holds it under another key, loss.set_keys({name}=<key>)."
            )
        return value

    def _check_shape(self, value: torch.Tensor, name: str, shape: tuple[int, ...]) -> None:
        """An error naming the key ``name`` and what it should hold if ``value`` is not of
        ``shape``."""
        if value.shape != shape:
            key = getattr(self.tensor_keys, name)
            raise ValueError(
                f"MAPOCALoss reads {key!r}, {_KEY_CONTENTS[name]}, with shape {list(shape)} "
                f"here; got {list(value.shape)}."
            )

    def _team_reward(
        self,
        tensordict: TensorDictBase,
        agent_mask: torch.Tensor | None,
        agent_shape: torch.Size,
    ) -> torch.Tensor:
        """The team reward [*B, 1] from a team [*B, 1] or per-agent [*B, K, 1] reward."""
        reward = self._read(tensordict, "reward", step="next")
        if not _is_per_agent(reward, ("next", *_as_tuple(self.tensor_keys.reward)), agent_shape):
            return reward
        if agent_mask is not None:
            reward = torch.where(agent_mask.unsqueeze(-1), reward, 0.0)
        team_reward = reward.sum(-2)
        if self.team_reward_reduction == "mean":
            present = (
                reward.shape[-2]
                if agent_mask is None
                else agent_mask.sum(-1, keepdim=True).clamp_min(1)
            )
            team_reward = team_reward / present
        return team_reward

    def _team_flag(
        self,
        tensordict: TensorDictBase,
        name: str,
        agent_mask: torch.Tensor | None,
        agent_shape: torch.Size,
    ) -> torch.Tensor:
        """A team flag [*B, 1] from a team [*B, 1] or per-agent [*B, K, 1] flag under "next":
        true for the team when true for every present agent."""
        flag = self._read(tensordict, name, step="next").bool()
        key = ("next", *_as_tuple(getattr(self.tensor_keys, name)))
        if not _is_per_agent(flag, key, agent_shape):
            return flag
        if agent_mask is not None:
            flag = flag | ~agent_mask.unsqueeze(-1)
        return flag.all(-2)

    # Python-side bookkeeping: under torch.compile it runs eagerly after the loss's graph
    # (traced, it would recompile the loss whenever the record changes)
    @torch.compiler.disable
    def _watch_backward(self, out: TensorDict) -> None:
        """Records which of the two critic terms of ``out`` the next backward pass goes through.

        Each term is replaced by a view whose hook records it: an eager view, which only a
        backward pass from the term itself reaches (a compiled graph's backward computes the
        gradient of every output, used or not, and would fire a hook on the term itself).
        """
        terms = ("loss_critic", "loss_baseline")
        if not all(out[name].requires_grad for name in terms):
            return
        reached = dict.fromkeys(terms, False)
        for name in terms:
            term = out[name].view_as(out[name])
            term.register_hook(functools.partial(_mark_reached, reached, name))
            out.set(name, term)
        self._backward_reached = reached

    @torch.compiler.disable
    def _warn_if_baseline_left_out(self) -> None:
        """Warns once if a backward pass went through ``loss_critic`` but not ``loss_baseline``:
        a MAPPO loop's sum, under which the baselines, and so the advantages, never learn."""
        reached = self._backward_reached
        if self._warned_baseline_left_out or reached is None:
            return
        if reached["loss_critic"] and not reached["loss_baseline"]:
            self._warned_baseline_left_out = True
            warnings.warn(
                "MAPOCALoss: the last backward pass went through loss_critic but not "
                "loss_baseline, so the counterfactual baselines, from which every agent's "
                "advantage comes, did not train. Sum every loss_* term of the output, "
                "sum(v for k, v in losses.items() if k.startswith('loss_')), rather than "
                "MAPPO's loss_objective + loss_critic + loss_entropy.",
                UserWarning,
                stacklevel=2,
            )

    def _agent_mask(
        self, tensordict: TensorDictBase, baseline: torch.Tensor
    ) -> torch.Tensor | None:
        """The presence mask [*B, K] (bool), or None when every agent is present."""
        mask = tensordict.get(self.tensor_keys.mask, None)
        if mask is None:
            return None
        agent_shape = baseline.shape[:-1]
        if mask.shape == (*agent_shape, 1):
            mask = mask.squeeze(-1)
        if mask.shape != agent_shape:
            raise ValueError(
                f"The agent mask {self.tensor_keys.mask!r} has shape {list(mask.shape)}, "
                f"expected {list(agent_shape)}."
            )
        return mask.bool()

    def _regression_loss(
        self,
        estimate: torch.Tensor,
        old_estimate: torch.Tensor,
        target: torch.Tensor,
        *,
        mask: torch.Tensor | None,
    ) -> tuple[torch.Tensor, torch.Tensor | None]:
        """Masked mean of d(estimate, target), pessimistically clipped around the old estimate."""
        loss = distance_loss(estimate, target, self.loss_critic_type)
        if self.clip_value is None:
            return _masked_mean(loss, mask), None
        change = estimate - old_estimate
        clipped_change = change.clamp(-self.clip_value, self.clip_value)
        clipped_loss = distance_loss(old_estimate + clipped_change, target, self.loss_critic_type)
        with torch.no_grad():
            clip_fraction = _masked_mean((change != clipped_change).to(loss.dtype), mask)
        return _masked_mean(torch.maximum(loss, clipped_loss), mask), clip_fraction


_CRITICS = ("value_network", "baseline_network")
"""The loss's critics, as :attr:`MAPOCALoss.critic_network_params` names their parameters."""


def _as_tuple(key: NestedKey) -> tuple[str, ...]:
    return (key,) if isinstance(key, str) else tuple(key)


def _flatten_key(key: NestedKey) -> NestedKey:
    key = _as_tuple(key)
    return key[0] if len(key) == 1 else key


def _time_dim(tensordict: TensorDictBase) -> int:
    """The batch dim marked "time", else the last one (torchrl's convention)."""
    names = tensordict.names
    return names.index("time") if "time" in names else tensordict.batch_dims - 1


def _mark_reached(reached: dict[str, bool], name: str, grad: torch.Tensor) -> None:
    reached[name] = True


def _is_per_agent(value: torch.Tensor, key: NestedKey, agent_shape: torch.Size) -> bool:
    """Whether ``value`` is per agent [*B, K, 1] rather than for the team [*B, 1]; an error
    naming ``key`` if it is neither."""
    if value.shape == (*agent_shape[:-1], 1):
        return False
    if value.shape == (*agent_shape, 1):
        return True
    raise ValueError(
        f"MAPOCALoss reads {_flatten_key(key)!r} for the team, [*B, 1] = "
        f"{[*agent_shape[:-1], 1]}, or per agent, [*B, K, 1] = {[*agent_shape, 1]}; "
        f"got {list(value.shape)}."
    )


def _per_agent(value: torch.Tensor, agent_shape: torch.Size, what: str) -> torch.Tensor:
    """One value per agent [*B, K]: as is, or summed over the action dims of [*B, K, A]."""
    if value.shape == agent_shape:
        return value
    if value.shape[:-1] == agent_shape:
        return value.sum(-1)
    raise ValueError(
        f"Expected the {what} per agent {list(agent_shape)} or per action dim "
        f"{[*agent_shape, 'A']}, got {list(value.shape)}."
    )


def _entropy(dist: d.Distribution) -> torch.Tensor:
    """Analytic entropy, or a one-sample estimate where the distribution has none."""
    with contextlib.suppress(NotImplementedError):
        return dist.entropy()
    sample = dist.rsample() if dist.has_rsample else dist.sample()
    return -dist.log_prob(sample)


def _masked_mean(value: torch.Tensor, mask: torch.Tensor | None) -> torch.Tensor:
    if mask is None:
        return value.mean()
    # torch.where, not a product: masked entries may be inf and inf * 0 is nan.
    return torch.where(mask, value, 0.0).sum() / mask.sum().clamp_min(1)


def _masked_standardize(advantage: torch.Tensor, agent_mask: torch.Tensor | None) -> torch.Tensor:
    """(A - mean) / (std + eps) over every present entry of A [*B, K, 1]."""
    mask = None if agent_mask is None else agent_mask.unsqueeze(-1)
    mean = _masked_mean(advantage, mask)
    std = _masked_mean((advantage - mean).square(), mask).sqrt()
    return (advantage - mean) / (std + _ADVANTAGE_STD_EPS)


def _least_variance_weight(
    residual: torch.Tensor, difference: torch.Tensor, mask: torch.Tensor | None
) -> torch.Tensor:
    """The w in [0, 1] for which residual - w * difference varies least over the present
    entries (G - V - w (b_i - V): the blend of V and b_i with the least noisy advantage), a
    regression slope Cov / Var, clipped."""
    residual = residual - _masked_mean(residual, mask)
    difference = difference - _masked_mean(difference, mask)
    covariance = _masked_mean(residual * difference, mask)
    variance = _masked_mean(difference.square(), mask)
    return (covariance / (variance + torch.finfo(variance.dtype).eps)).clamp(0.0, 1.0)


def _explained_variance(
    target: torch.Tensor, prediction: torch.Tensor, mask: torch.Tensor | None
) -> torch.Tensor:
    """1 - Var(target - prediction) / Var(target), over the present entries."""
    residual = target - prediction
    residual_var = _masked_mean((residual - _masked_mean(residual, mask)).square(), mask)
    target_var = _masked_mean((target - _masked_mean(target, mask)).square(), mask)
    return 1.0 - residual_var / (target_var + torch.finfo(target.dtype).eps)


def _effective_sample_fraction(log_ratio: torch.Tensor, mask: torch.Tensor | None) -> torch.Tensor:
    """Kish's effective sample size of the importance weights, over their number: in (0, 1]."""
    if mask is None:
        count = log_ratio.numel()
    else:
        # exp(-inf) = 0 drops absent agents from both sums without a host sync.
        log_ratio = torch.where(mask, log_ratio, -torch.inf)
        count = mask.sum().clamp_min(1)
    log_ratio = log_ratio.flatten()
    log_ess = 2 * log_ratio.logsumexp(0) - (2 * log_ratio).logsumexp(0)
    return log_ess.exp() / count
