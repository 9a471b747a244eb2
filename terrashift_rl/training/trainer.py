"""On-policy training on batched TerraShift environments: collect, estimate, update, checkpoint.

:class:`OnPolicyTrainer` owns the environment, the networks, the loss and the optimiser; the loss
is the algorithm ``train.algo`` names (:mod:`terrashift_rl.training.algorithms`: MA-POCA, MAPPO
or IPPO on the same trunk and policy head). One iteration collects ``steps_per_iteration``
decisions in every environment with the stochastic policy (dropout off), runs the algorithm's
value-estimation pass once with the collection-time parameters (for MA-POCA, GAE from the
centralised value and counterfactual baselines), then runs ``epochs`` passes of shuffled
mini-batches. Mini-batches are whole per-environment sequences, and the GRU runs over
them from the state stored at each sequence start (torchrl's recurrent mode). On CUDA the
actor's step and each mini-batch update are replayed as CUDA graphs (``cuda_graphs``); the
update only where the algorithm's loss runs without host synchronisation (MA-POCA's).

The collection loop is written out (``env.step_and_maybe_reset``) rather than delegated to a
collector, because a checkpoint has to hold the tensordict carried between iterations and the
simulator state: a resumed run then continues exactly where the killed one stopped.

Built in each process of a torch.distributed group (``torchrun``), the trainers train
data-parallel (:mod:`terrashift_rl.training.distributed`): each collects from its own
environments, and all take the same steps on gradients averaged over the processes.
"""

from __future__ import annotations

import contextlib
import math
import os
import time
from collections.abc import Callable, Iterator
from dataclasses import asdict
from typing import Any

import torch
from tensordict import TensorDictBase
from torchrl.envs import Compose, InitTracker, TransformedEnv
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.modules import set_recurrent_mode

from terrashift_rl.envs import TerraShiftEnv
from terrashift_rl.envs.baselines import ScriptedHeuristicPolicy
from terrashift_rl.modules import TerraShiftNetworks, keys
from terrashift_rl.sim import TerraShiftConfig
from terrashift_rl.sim.types import ACTION_NAMES
from terrashift_rl.training import distributed
from terrashift_rl.training.graphs import CudaGraphed
from terrashift_rl.training.schedules import LinearSchedule
from terrashift_rl.training.settings import TrainConfig

# Collection writes these as by-products of acting; every pass of the update recomputes them
# with the current parameters, so the batch does not keep them. (It keeps the distribution's
# parameters, 12 numbers per agent-step, for `concentration_metrics`.)
_RECOMPUTED_KEYS = (keys.AGENT_EMBEDDING,)

_KL_STEP = 1.5
"""Factor by which the adaptive schedule moves the learning rates after a mini-batch."""
_RANK_KEYS = ("torch_rng", "cuda_rng", "simulator", "carry")
"""What each process of a data-parallel run holds of its own in a checkpoint."""
_SUMMED_METRICS = ("episodes", "env_steps_per_s", "collection_steps_per_s")
"""Metrics of a data-parallel iteration that add up over the processes (the others average)."""


def make_training_env(
    env_config: TerraShiftConfig,
    networks: TerraShiftNetworks,
    *,
    num_envs: int,
    device: torch.device,
    seed: int,
) -> TransformedEnv:
    """TerraShift with the transforms the recurrent policy needs: ``is_init`` and its state."""
    base = TerraShiftEnv(env_config, num_envs=num_envs, device=device, seed=seed)
    primer = networks.make_tensordict_primer(env_config.num_agents)
    return TransformedEnv(base, Compose(InitTracker(), primer))


class OnPolicyTrainer:
    """Collects and learns with the algorithm ``config.algo`` names; holds everything a
    checkpoint needs.

    Attributes:
        algorithm: the loss and what the loop needs of it
            (:class:`~terrashift_rl.training.algorithms.Algorithm`).
        loss: ``algorithm.loss``.

    Args:
        env: a batched environment from :func:`make_training_env`.
        networks: the actor, value and baseline networks sharing one trunk.
        config: training hyper-parameters.
    """

    def __init__(self, env: TransformedEnv, networks: TerraShiftNetworks, config: TrainConfig):
        config.validate()
        self.env = env
        self.networks = networks
        self.config = config
        self.device = env.device
        # the estimation pass runs no bigger pieces than a training mini-batch: same memory bound
        max_batch = math.ceil(config.num_envs / config.minibatches)
        self.algorithm = config.loss.make(networks, max_batch=max_batch)
        self.loss = self.algorithm.loss
        distributed.broadcast_from_main([networks, self.algorithm.networks])
        if config.compile:
            networks.compile_networks()
            for head in self.algorithm.networks.values():
                head.module.compile()
        loss = config.loss
        self.teacher = (
            ScriptedHeuristicPolicy(env.base_env.config)
            if getattr(loss, "teacher_coeff", 0.0)  # MA-POCA's alone
            else None
        )
        policy_parameters = [*networks.trunk.parameters(), *networks.policy_head.parameters()]
        self._policy_parameters = policy_parameters
        critic_parameters = [p for critic in self.algorithm.critics for p in critic.parameters()]
        self.optimizer = torch.optim.AdamW(
            [
                {"params": policy_parameters, "lr": config.lr_trunk_policy},
                {"params": critic_parameters, "lr": config.lr_value_baseline},
            ],
            weight_decay=config.weight_decay,
        )
        self._base_lrs = [config.lr_trunk_policy, config.lr_value_baseline]
        self._graphs = config.cuda_graphs and self.device.type == "cuda"
        if self.device.type == "cuda":
            torch.backends.cuda.matmul.allow_tf32 = config.tf32
        if config.deterministic:
            # cuBLAS reads this when it first allocates its workspace
            os.environ.setdefault("CUBLAS_WORKSPACE_CONFIG", ":4096:8")
            torch.use_deterministic_algorithms(True)
        self._prepare_optimizer()
        self._parameters = [p for group in self.optimizer.param_groups for p in group["params"]]
        # tensors updated in place, so that a captured update reads each iteration's value
        self._max_grad_norm = torch.tensor(config.max_grad_norm_start, device=self.device)
        # factors on the base learning rates of the trunk and policy, and of the critics; an
        # adaptive schedule moves the first inside the update
        self._lr_scales = torch.ones(2, device=self.device)
        self._actor_inputs = networks.actor.in_keys
        self._actor_outputs = [k for k in networks.actor.out_keys if k not in _RECOMPUTED_KEYS]
        self._reset_graphs()
        n = config.schedule_iterations
        self.schedules = {
            "lr_factor": LinearSchedule(1.0, config.lr_end_factor, n),
            "clip_epsilon": LinearSchedule(loss.clip_epsilon_start, loss.clip_epsilon_end, n),
            "entropy_coeff": LinearSchedule(loss.entropy_coeff_start, loss.entropy_coeff_end, n),
            "clip_value": LinearSchedule(loss.clip_value_start, loss.clip_value_end, n),
            "max_grad_norm": LinearSchedule(
                config.max_grad_norm_start, config.max_grad_norm_end, n
            ),
        }
        if self.teacher is not None:
            self.schedules["teacher_coeff"] = LinearSchedule(
                loss.teacher_coeff, loss.teacher_coeff_end, loss.teacher_iterations
            )
        self.iteration = 0
        self.env_steps = 0
        self._carry: TensorDictBase | None = None

    # --- one iteration ---------------------------------------------------------------------
    def train_iteration(self) -> dict[str, float]:
        """Collects one batch and learns from it; returns the iteration's metrics."""
        start = time.perf_counter()
        data = self.collect()
        collected = time.perf_counter()
        metrics = self.update(data)
        self._check_finite(metrics)
        self._synchronize()
        finished = time.perf_counter()
        frames = data.numel()
        self.iteration += 1
        self.env_steps += frames * distributed.world_size()
        metrics.update(episode_metrics(data))
        metrics.update(concentration_metrics(data))
        metrics.update(action_medians(data))
        metrics["env_steps_per_s"] = frames / (finished - start)
        metrics["collection_steps_per_s"] = frames / (collected - start)
        metrics["update_seconds"] = finished - collected
        return distributed.combine_metrics(metrics, summed=_SUMMED_METRICS)

    @torch.no_grad()
    def collect(self) -> TensorDictBase:
        """``steps_per_iteration`` decisions in every environment; returns [num_envs, T]."""
        if self._carry is None:
            self._carry = self.env.reset()
            if self.config.stagger_episodes:
                self.env.base_env.stagger_episodes()
        self.networks.eval()  # no dropout: the stored log-probs are the policy's own
        td = self._carry
        frames = []
        with set_exploration_type(ExplorationType.RANDOM), self._autocast():
            for _ in range(self.config.steps_per_iteration):
                inputs = td.select(*self._actor_inputs, strict=False)
                td.update(self._actor_step(inputs).clone())  # a graph's outputs are reused
                step, td = self.env.step_and_maybe_reset(td)
                frames.append(step)
        self._carry = td
        data = torch.stack(frames, dim=1)
        if self.teacher is not None:
            observed = data.select(keys.AGENT_OBSERVATION, keys.OBJECTS, keys.OBJECTS_MASK)
            data.set(self.loss.tensor_keys.teacher_action, self.teacher(observed).get(keys.ACTION))
        return data

    def _act(self, tensordict: TensorDictBase) -> TensorDictBase:
        return self.networks.actor(tensordict).select(*self._actor_outputs)

    def update(self, data: TensorDictBase) -> dict[str, float]:
        """Value estimation once, then epochs of shuffled mini-batches of sequences."""
        config = self.config
        warmup = self.iteration < config.critic_warmup_iterations
        self._apply_schedules()
        self._train_mode(False)
        start = time.perf_counter()
        with self._autocast():
            self.algorithm.estimate(data)
        self._synchronize()
        estimation_seconds = time.perf_counter() - start
        self._train_mode(True)
        sums: dict[str, torch.Tensor] = {}
        count = 0
        for _ in range(config.epochs):
            order = torch.randperm(data.shape[0], device=self.device)
            for index in order.chunk(config.minibatches):
                step = (len(index), warmup)  # one graph per mini-batch size and kind of step
                if step not in self._update_steps:
                    function = self._critic_step if warmup else self._update_step
                    self._update_steps[step] = (
                        self._graphed(function) if self.algorithm.capturable else function
                    )
                out = self._update_steps[step](data[index])
                for key, value in out.items():
                    # per-element diagnostics (torchrl's explained variance, ESS) are averaged
                    sums[key] = sums.get(key, 0.0) + value.float().mean()
                count += 1
        # over every process, so that each reaches the same verdict in _check_finite
        means = distributed.average(torch.stack(list(sums.values())) / count)
        metrics = dict(zip(sums, means.tolist(), strict=True))
        metrics["lr_trunk_policy"] = float(self.optimizer.param_groups[0]["lr"])
        metrics["critic_warmup"] = float(warmup)
        metrics["clip_epsilon"] = float(self.loss.clip_epsilon)
        metrics["entropy_coeff"] = float(self.loss.entropy_coeff)
        if self.teacher is not None:
            metrics["teacher_coeff"] = float(self.loss.teacher_coeff)
        metrics["estimation_seconds"] = estimation_seconds
        return metrics

    def _update_step(self, batch: TensorDictBase) -> TensorDictBase:
        """One gradient step on a mini-batch; returns the loss terms and diagnostics."""
        with set_recurrent_mode(True), self._autocast():
            out = self.loss(batch)
        if self.config.lr_schedule == "adaptive":
            self._adapt_learning_rate(out.get("kl_approx"))
        total = sum(value for key, value in out.items() if key.startswith("loss_"))
        return self._step(out, total, frozen=())

    def _critic_step(self, batch: TensorDictBase) -> TensorDictBase:
        """A gradient step of the critics alone: the trunk and the policy, whose parameters get
        no gradient, are left exactly as they are (AdamW skips them)."""
        with set_recurrent_mode(True), self._autocast():
            out = self.loss(batch)
        total = sum(out.get(term) for term in self.algorithm.critic_terms)
        return self._step(out, total, frozen=self._policy_parameters)

    def _step(
        self, out: TensorDictBase, total: torch.Tensor, frozen: list[torch.nn.Parameter] | tuple
    ) -> TensorDictBase:
        self.optimizer.zero_grad(set_to_none=True)
        total.backward()
        for parameter in frozen:
            parameter.grad = None
        # clip_grad_norm_ reads max_norm on the host; this keeps it a tensor
        stepped = [p for p in self._parameters if p.grad is not None]
        distributed.average_gradients(stepped)
        grads = [p.grad for p in stepped]
        grad_norm = torch.nn.utils.get_total_norm(grads)
        torch._foreach_mul_(grads, (self._max_grad_norm / (grad_norm + 1e-6)).clamp(max=1.0))
        self.optimizer.step()
        out.set("grad_norm", grad_norm)
        out.set("loss_total", total)
        return out.detach()

    def _check_finite(self, metrics: dict[str, float]) -> None:
        """Raises ``FloatingPointError`` naming the first loss term, gradient norm or parameter
        that an update made non-finite, so that a run stops before it saves them. The metrics are
        on the host already; the parameters cost one host synchronisation per iteration."""
        for name, value in metrics.items():
            if (name.startswith("loss_") or name == "grad_norm") and not math.isfinite(value):
                raise self._non_finite(f"{name} = {value}")
        parameters = dict(self._named_parameters())
        finite = torch.stack([parameter.isfinite().all() for parameter in parameters.values()])
        if not finite.all():
            first = list(parameters)[int(finite.logical_not().nonzero()[0])]
            raise self._non_finite(f"parameter {first} holds non-finite values")

    def _non_finite(self, what: str) -> FloatingPointError:
        return FloatingPointError(
            f"iteration {self.iteration + 1} made {what}; lower the learning rates "
            "(train.lr_trunk_policy, train.lr_value_baseline) first"
        )

    # --- checkpoints -----------------------------------------------------------------------
    def state_dict(self) -> dict[str, Any]:
        """Everything a resumed run needs to continue exactly: weights (:meth:`weights_state_dict`),
        optimiser, return statistics, counters, random states, the simulator state and the
        tensordict carried between iterations.

        In a data-parallel run every process must call it together: rank 0's state then also
        holds ``world_size`` and, in ``rank_states``, the random states, simulator state and
        carried tensordict of ranks 1, 2, ... (the rest all ranks share)."""
        normalizer = self.algorithm.value_normalizer
        state = {
            **self.weights_state_dict(),
            "optimizer": self.optimizer.state_dict(),
            "iteration": self.iteration,
            "env_steps": self.env_steps,
            "train_config": asdict(self.config),
            "value_normalizer": (None if normalizer is None else normalizer.state_dict()),
            "torch_rng": torch.get_rng_state(),
            "cuda_rng": torch.cuda.get_rng_state_all() if torch.cuda.is_available() else None,
            "simulator": self.env.base_env.sim.state_dict(),
            "carry": None if self._carry is None else self._carry.to("cpu"),
        }
        if distributed.is_distributed():
            own = {key: state[key] for key in _RANK_KEYS}
            own["simulator"] = {name: value.cpu() for name, value in own["simulator"].items()}
            gathered = distributed.gather_to_main(own)
            state["world_size"] = distributed.world_size()
            if gathered is not None:
                state["rank_states"] = gathered[1:]
        return state

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restores a :meth:`state_dict` taken from a run with the same settings. In a
        data-parallel run each rank takes its own environments and random states from it; a rank
        the checkpoint's run did not have (it had fewer processes) keeps its freshly seeded ones
        and starts new episodes."""
        algo = state["algo"]
        if algo != self.config.algo:
            raise ValueError(
                f"the checkpoint was trained with algo={algo}; resume with the same setting"
            )
        self.networks.load_state_dict(state["networks"])
        self.algorithm.networks.load_state_dict(state["algorithm_networks"])
        self.optimizer.load_state_dict(state["optimizer"])
        normalizer = self.algorithm.value_normalizer
        if (normalizer is None) != (state.get("value_normalizer") is None):
            raise ValueError(
                "the checkpoint was trained with loss.normalize_value="
                f"{normalizer is None}; resume with the same setting"
            )
        if normalizer is not None:
            normalizer.load_state_dict(state["value_normalizer"])
        self.iteration = state["iteration"]
        self.env_steps = state["env_steps"]
        own = distributed.rank_entries(state, _RANK_KEYS)
        if own is not None:
            torch.set_rng_state(own["torch_rng"])
            if own["cuda_rng"] is not None and torch.cuda.is_available():
                torch.cuda.set_rng_state_all(own["cuda_rng"])
            self.env.base_env.sim.load_state_dict(
                {name: value.to(self.device) for name, value in own["simulator"].items()}
            )
            carry = own["carry"]
            self._carry = None if carry is None else carry.to(self.device)
        self._prepare_optimizer()
        # an adaptive rate continues from where the checkpoint's put it
        self._lr_scales[0].fill_(float(self.optimizer.param_groups[0]["lr"]) / self._base_lrs[0])
        self._reset_graphs()  # the optimiser's state tensors are new

    def weights_state_dict(self) -> dict[str, Any]:
        """The weights that evaluation and finetuning read: ``networks`` (the shared trunk and
        the heads of :class:`~terrashift_rl.modules.TerraShiftNetworks`, all the actor needs),
        ``algorithm_networks`` (the algorithm's own, IPPO's per-agent value head; empty for the
        others) and ``algo``, the algorithm they were trained with."""
        return {
            "networks": self.networks.state_dict(),
            "algorithm_networks": self.algorithm.networks.state_dict(),
            "algo": self.config.algo,
        }

    def load_weights(self, state: dict[str, Any]) -> None:
        """Starts from a checkpoint's weights (finetuning): the shared networks, and the
        algorithm's own networks where the checkpoint was trained with the same algorithm;
        otherwise these keep their fresh initialisation. The optimiser, the schedules and the
        return statistics start afresh. ``state`` is a :meth:`weights_state_dict` or a
        :meth:`state_dict` (a checkpoint of an earlier layout converted by
        :func:`~terrashift_rl.training.checkpoint.upgrade`)."""
        self.networks.load_state_dict(state["networks"])
        if state["algo"] == self.config.algo:
            self.algorithm.networks.load_state_dict(state["algorithm_networks"])

    # --- helpers ---------------------------------------------------------------------------
    def _adapt_learning_rate(self, kl: torch.Tensor) -> None:
        """RSL-RL's rule on the KL estimate of the mini-batch about to be stepped: the trunk and
        policy's rate moves by ``_KL_STEP`` when the KL leaves [target / 2, 2 target]. With CUDA
        graphs the rates are tensors and this runs inside the captured update, without a host
        synchronisation."""
        target = self.config.desired_kl
        kl = distributed.average(kl.detach().float())
        step = torch.where(
            kl > 2.0 * target,
            1.0 / _KL_STEP,
            torch.where(kl < 0.5 * target, _KL_STEP, 1.0),
        )
        base = self.config.lr_trunk_policy
        scale = self._lr_scales[0]
        scale.mul_(step).clamp_(self.config.lr_min / base, self.config.lr_max / base)
        self._set_learning_rates()

    def _set_learning_rates(self) -> None:
        groups = self.optimizer.param_groups
        for group, base, scale in zip(groups, self._base_lrs, self._lr_scales, strict=True):
            if isinstance(group["lr"], torch.Tensor):
                group["lr"].copy_(base * scale)
            else:
                group["lr"] = base * float(scale)

    def _apply_schedules(self) -> None:
        factor = self.schedules["lr_factor"](self.iteration)
        self._lr_scales[1].fill_(factor)
        if self.config.lr_schedule == "linear":
            self._lr_scales[0].fill_(factor)
        self._set_learning_rates()
        # the loss's coefficients are buffers: assigning a float copies in place
        for name in ("clip_epsilon", "entropy_coeff", "clip_value"):
            setattr(self.loss, name, self.schedules[name](self.iteration))
        if self.teacher is not None:
            self.loss.teacher_coeff = self.schedules["teacher_coeff"](self.iteration)
        self._max_grad_norm.fill_(self.schedules["max_grad_norm"](self.iteration))

    def _prepare_optimizer(self) -> None:
        """With CUDA graphs, AdamW must be capturable (its step count on the device) and its
        learning rates tensors; this also converts the state of a checkpoint taken either way."""
        for group in self.optimizer.param_groups:
            group["capturable"] = self._graphs
            lr = float(group["lr"])
            group["lr"] = torch.tensor(lr, device=self.device) if self._graphs else lr
        step_device = self.device if self._graphs else torch.device("cpu")
        for state in self.optimizer.state.values():
            if "step" in state:
                state["step"] = state["step"].to(step_device, torch.float32)

    def _graphed(self, function: Callable[[TensorDictBase], TensorDictBase]) -> Callable:
        return CudaGraphed(function) if self._graphs else function

    def _train_mode(self, mode: bool) -> None:
        self.networks.train(mode)
        self.algorithm.networks.train(mode)

    def _named_parameters(self) -> Iterator[tuple[str, torch.nn.Parameter]]:
        yield from self.networks.named_parameters()
        yield from self.algorithm.networks.named_parameters(prefix="algorithm_networks")

    def _reset_graphs(self) -> None:
        self._actor_step = self._graphed(self._act)
        self._update_steps: dict[tuple[int, bool], Callable] = {}

    def _autocast(self) -> contextlib.AbstractContextManager:
        if self.config.bf16 and self.device.type == "cuda":
            # cached casts of the weights are freed on exit: a graph must not keep them
            return torch.autocast("cuda", dtype=torch.bfloat16, cache_enabled=not self._graphs)
        return contextlib.nullcontext()

    def _synchronize(self) -> None:
        if self.device.type == "cuda":
            torch.cuda.synchronize(self.device)


MAPOCATrainer = OnPolicyTrainer
"""The trainer's name from when MA-POCA was its only algorithm."""


def episode_metrics(data: TensorDictBase) -> dict[str, float]:
    """Reward per decision and, over the episodes that ended in ``data``, goals and losses.

    ``success_rate`` is goals over resolved objects (goals plus out-of-bounds).
    """
    nxt = data.get("next")
    # every agent holds the team reward
    metrics = {"reward_per_decision": nxt.get(("agents", "reward"))[..., 0, 0].mean().item()}
    done = nxt.get("done").squeeze(-1)
    episodes = int(done.sum())
    metrics["episodes"] = float(episodes)
    if episodes:
        goals = nxt.get("episode_goals").squeeze(-1)[done].float()
        lost = nxt.get("episode_out_of_bounds").squeeze(-1)[done].float()
        resolved = goals.sum() + lost.sum()
        metrics["goals_per_episode"] = goals.mean().item()
        metrics["out_of_bounds_per_episode"] = lost.mean().item()
        metrics["success_rate"] = (goals.sum() / resolved).item() if resolved > 0 else math.nan
    return metrics


def concentration_metrics(data: TensorDictBase) -> dict[str, float]:
    """How sure the policy is of each action, per action dimension: for a Beta policy
    ``concentration_<name>``, the median over the collected agent-steps of alpha + beta (a
    policy whose amplitude grows more concentrated than its velocities tends not to steer);
    for a Gaussian one (``model.distribution=normal``) ``action_std_<name>``, its standard
    deviation, the same in every state."""
    if keys.NORMAL_SCALE in data.keys(include_nested=True):
        name, spread = "action_std", data.get(keys.NORMAL_SCALE)
    else:
        name = "concentration"
        spread = data.get(keys.BETA_CONCENTRATION1) + data.get(keys.BETA_CONCENTRATION0)
    medians = _lower_medians(spread)
    return {f"{name}_{action}": value for action, value in zip(ACTION_NAMES, medians, strict=True)}


def action_medians(data: TensorDictBase) -> dict[str, float]:
    """Where the policy acts, per action dimension: ``action_median_<name>``, the median over
    the collected agent-steps of the action the actuators received (clipped to [-1, 1]): beside
    a dimension's concentration, whether the policy holds it near one value, and which."""
    medians = _lower_medians(data.get(keys.ACTION).clamp(-1.0, 1.0))
    return {
        f"action_median_{name}": value for name, value in zip(ACTION_NAMES, medians, strict=True)
    }


def _lower_medians(values: torch.Tensor) -> list[float]:
    """The lower median of each action dimension (the last) over all the others, through a
    sort: ``median(dim)`` has no deterministic CUDA implementation."""
    ordered = values.float().flatten(0, -2).sort(dim=0).values
    return ordered[(len(ordered) - 1) // 2].tolist()


def iterate_until(
    trainer: OnPolicyTrainer, *, total_env_steps: int, deadline: float | None
) -> Iterator[dict[str, float]]:
    """Runs iterations until ``total_env_steps`` or the wall-clock ``deadline``
    (``time.monotonic()`` value) is reached, yielding each iteration's metrics."""
    while trainer.env_steps < total_env_steps:
        if deadline is not None and distributed.any_process(time.monotonic() >= deadline):
            return
        yield trainer.train_iteration()


def planned_env_steps(
    env_steps: int,
    per_iteration: int,
    total_env_steps: int,
    *,
    seconds_left: float | None = None,
    seconds_per_iteration: float | None = None,
) -> int:
    """The env-steps at which :func:`iterate_until` will stop, from ``env_steps`` done and
    ``per_iteration`` per iteration: the first iteration's end at or past ``total_env_steps``,
    or earlier the last iteration that starts within ``seconds_left`` (the deadline) at
    ``seconds_per_iteration``.

    Example:
        >>> planned_env_steps(0, 1024, 100_000)  # 98 iterations
        100352
        >>> planned_env_steps(2048, 1024, 100_000, seconds_left=45.0, seconds_per_iteration=10.0)
        7168
    """
    iterations = math.ceil(max(total_env_steps - env_steps, 0) / per_iteration)
    if seconds_left is not None and seconds_per_iteration:
        iterations = min(iterations, math.ceil(max(seconds_left, 0.0) / seconds_per_iteration))
    return env_steps + iterations * per_iteration
