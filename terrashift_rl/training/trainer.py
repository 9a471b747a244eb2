"""On-policy training: collect, estimate, update, checkpoint.

:class:`OnPolicyTrainer` is handed its parts: an environment and a policy that collect, the
algorithm (:mod:`terrashift_rl.training.algorithms`: a loss and its value-estimation pass), an
optimiser, and hooks (:class:`TrainerHook`) for what belongs to the scene; it knows nothing of
the scene (TerraShift's parts and hooks: :mod:`terrashift_rl.training.terrashift`). One
iteration collects ``steps_per_iteration`` decisions in every environment with the stochastic
policy (dropout off), runs the algorithm's value-estimation pass once with the collection-time
parameters (for MA-POCA, GAE from the centralised value and counterfactual baselines), then runs
``epochs`` passes of shuffled mini-batches. Mini-batches are whole per-environment sequences,
and a recurrent policy runs over them from the state stored at each sequence start (torchrl's
recurrent mode). On CUDA the actor's step and each mini-batch update are replayed as CUDA graphs
(``cuda_graphs``); the update only where the algorithm's loss runs without host
synchronisation (MA-POCA's). So is the step of an evaluation's policy
(:meth:`OnPolicyTrainer.evaluation_policy`).

The collection loop is written out (``env.step_and_maybe_reset``) rather than delegated to a
collector, because a checkpoint has to hold the tensordict carried between iterations and the
scene's state (a hook's): a resumed run then continues exactly where the killed one stopped.

Built in each of N processes of a torch.distributed group (``torchrun``), the trainers train
data-parallel (:mod:`terrashift_rl.training.distributed`): each collects from its own
environments and splits its batch N times finer (:attr:`OnPolicyTrainer.minibatches`), and all
take the same steps on gradients averaged over the processes.
"""

from __future__ import annotations

import contextlib
import functools
import math
import os
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import asdict
from typing import Any

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.envs import EnvBase
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.modules import set_recurrent_mode

from terrashift_rl.training import distributed
from terrashift_rl.training.algorithms import Algorithm
from terrashift_rl.training.graphs import CudaGraphed
from terrashift_rl.training.schedules import training_schedules
from terrashift_rl.training.settings import TrainConfig

_KL_STEP = 1.5
"""Factor by which the adaptive schedule moves the learning rates after a mini-batch."""
_RANK_KEYS = ("torch_rng", "cuda_rng", "carry")
"""What each data-parallel process holds of its own in a checkpoint, besides its hooks' state."""
_SUMMED_METRICS = ("env_steps_per_s", "collection_steps_per_s")
"""The trainer's metrics that add up over the processes of a data-parallel run (others average)."""
_TERM_SETTINGS = {
    "loss_critic": "value_coeff",
    "loss_baseline": "baseline_coeff",
    "loss_entropy": "entropy_coeff_start",
    "loss_teacher": "teacher_coeff",
}
"""The loss setting that weighs each loss term: a suspect when the loss turns non-finite."""
_EXCHANGED = "exchanged"
"""The entry of a mini-batch's backward output that the processes average (gradients, KL)."""


class TrainerHook:
    """Work that belongs to a scene rather than to the algorithm, called by
    :class:`OnPolicyTrainer` at fixed points of each iteration (as BenchMARL's ``Callback`` and
    torchrl's trainer hooks are). Subclasses override what they need; every method does nothing
    by default. TerraShift's hooks are in :mod:`terrashift_rl.training.terrashift`.

    Attributes:
        summed_metrics: names of :meth:`metrics` that add up over the processes of a
            data-parallel run (counts); the others average.
        state_keys: the top-level checkpoint entries :meth:`state_dict` returns.
    """

    summed_metrics: tuple[str, ...] = ()
    state_keys: tuple[str, ...] = ()

    def on_reset(self, trainer: OnPolicyTrainer, tensordict: TensorDictBase) -> None:
        """After the first reset of a run's environments (not on a resume, whose environments
        carry on), with the reset's output."""

    def on_batch_collected(self, trainer: OnPolicyTrainer, data: TensorDictBase) -> None:
        """After each collection, before value estimation, with the batch ``[num_envs, T]``:
        may check it or write entries into it (a teacher's action)."""

    def metrics(self, trainer: OnPolicyTrainer, data: TensorDictBase) -> dict[str, float]:
        """After each update: the scene's metrics of the collected batch, logged with the
        iteration's."""
        return {}

    def state_dict(self) -> dict[str, Any]:
        """What this process holds of its own for a checkpoint (a simulator's state), under
        :attr:`state_keys`."""
        return {}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restores :meth:`state_dict`'s entries of this process."""


class OnPolicyTrainer:
    """Collects with a policy and learns with an algorithm; holds everything a checkpoint needs.
    It knows nothing of the scene: :func:`terrashift_rl.training.terrashift.make_trainer`
    builds TerraShift's, its scene's pieces as hooks (:class:`TrainerHook`).

    Attributes:
        algorithm: the loss and what the loop needs of it
            (:class:`~terrashift_rl.training.algorithms.Algorithm`).
        loss: ``algorithm.loss``.
        minibatches: mini-batches per epoch of this process's batch, ``config.minibatches``
            times the number of processes.

    Args:
        env: a batched environment; ``step_and_maybe_reset`` carries its episodes on.
        policy: the actor, writing the action and its log-probability.
        algorithm: the loss and its value-estimation pass.
        optimizer: two parameter groups, the policy's (trained at ``lr_trunk_policy``, frozen
            during a critic warm-up) then the critics' (at ``lr_value_baseline``); their
            learning rates at construction are the schedules' starts.
        config: training hyper-parameters.

    Keyword Args:
        networks: every network the policy and the critics run, saved in checkpoints as
            ``networks`` (the algorithm's own as ``algorithm_networks``).
        hooks: the scene's pieces, called in order.
    """

    def __init__(
        self,
        env: EnvBase,
        policy: TensorDictModuleBase,
        algorithm: Algorithm,
        optimizer: torch.optim.Optimizer,
        config: TrainConfig,
        *,
        networks: torch.nn.Module,
        hooks: Sequence[TrainerHook] = (),
    ):
        config.validate(processes=distributed.world_size())
        if len(optimizer.param_groups) != 2:
            raise ValueError(
                "the optimizer must have two parameter groups, the policy's then the critics', "
                f"got {len(optimizer.param_groups)}"
            )
        self.env = env
        self.policy = policy
        self.networks = networks
        self.config = config
        self.minibatches = config.minibatches_per_process(distributed.world_size())
        self.device = env.device
        self.algorithm = algorithm
        self.loss = algorithm.loss
        self.optimizer = optimizer
        self.hooks = list(hooks)
        distributed.broadcast_from_main([networks, algorithm.networks])
        self._policy_parameters = list(optimizer.param_groups[0]["params"])
        self._base_lrs = [float(group["lr"]) for group in optimizer.param_groups]
        self._graphs = config.cuda_graphs and self.device.type == "cuda"
        if self.device.type == "cuda":
            torch.backends.cuda.matmul.allow_tf32 = config.tf32
        if config.deterministic:
            # cuBLAS reads this when it first allocates its workspace
            os.environ.setdefault("CUBLAS_WORKSPACE_CONFIG", ":4096:8")
            torch.use_deterministic_algorithms(True)
        self._prepare_optimizer()
        self._parameters = [p for group in optimizer.param_groups for p in group["params"]]
        # tensors updated in place, so that a captured update reads each iteration's value
        self._max_grad_norm = torch.tensor(config.max_grad_norm_start, device=self.device)
        # factors on the base learning rates of the policy and of the critics; an adaptive
        # schedule moves the first inside the update
        self._lr_scales = torch.ones(2, device=self.device)
        self._actor_inputs = policy.in_keys
        self._actor_outputs = list(policy.out_keys)
        self._rank_keys = (*_RANK_KEYS, *(key for hook in self.hooks for key in hook.state_keys))
        self._summed_metrics = (
            *_SUMMED_METRICS,
            *(name for hook in self.hooks for name in hook.summed_metrics),
        )
        self._reset_graphs()
        self.schedules = training_schedules(config)
        self.iteration = 0
        self.env_steps = 0
        self.schedule_start = 0  # the iteration the schedules count from
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
        for hook in self.hooks:
            metrics.update(hook.metrics(self, data))
        metrics["env_steps_per_s"] = frames / (finished - start)
        metrics["collection_steps_per_s"] = frames / (collected - start)
        metrics["update_seconds"] = finished - collected
        return distributed.combine_metrics(metrics, summed=self._summed_metrics)

    @torch.no_grad()
    def collect(self) -> TensorDictBase:
        """``steps_per_iteration`` decisions in every environment; returns [num_envs, T]."""
        if self._carry is None:
            self._carry = self.env.reset()
            for hook in self.hooks:
                hook.on_reset(self, self._carry)
        self.policy.eval()  # no dropout: the stored log-probs are the policy's own
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
        for hook in self.hooks:
            hook.on_batch_collected(self, data)
        return data

    def set_env(self, env: EnvBase) -> None:
        """Collects from ``env`` (a curriculum's next stage, maybe of other shapes) from the
        next iteration on, from a reset; drops the graphs captured on the former's shapes. Under
        ``config.compile``, Dynamo's limit of compilations per network grows by one for the new
        shapes, lest a curriculum's ninth stage run its update eagerly."""
        if env.device != self.device:
            raise ValueError(f"the new env is on {env.device}, the trainer on {self.device}")
        self.env = env
        self._carry = None
        self._reset_graphs()
        if self.config.compile:
            torch._dynamo.config.recompile_limit += 1

    def restart_schedules(self) -> None:
        """Starts ``schedules`` again at the next iteration (a curriculum's next stage)."""
        self.schedule_start = self.iteration

    def evaluation_policy(
        self, exploration: ExplorationType
    ) -> Callable[[TensorDictBase], TensorDictBase]:
        """The policy acting with ``exploration`` as an evaluation plays it
        (:func:`~terrashift_rl.training.evaluation.evaluate_periodically`): outside collection's
        autocast, writing the policy's outputs into the tensordict it is given. With CUDA graphs
        its step is replayed as a graph captured under ``exploration``, one per exploration
        type and input shapes (a curriculum stage's evaluation scenes have their own), and kept
        for later evaluations until the trainer's graphs are reset."""

        def policy(tensordict: TensorDictBase) -> TensorDictBase:
            inputs = tensordict.select(*self._actor_inputs, strict=False)
            shapes = tuple(
                (key, value.shape, value.dtype) for key, value in inputs.items(True, True)
            )
            step = self._evaluation_steps.get((exploration, shapes))
            if step is None:
                act = functools.partial(self._act_with, exploration)
                step = self._evaluation_steps[exploration, shapes] = self._graphed(act)
            return tensordict.update(step(inputs).clone())  # a graph's outputs are reused

        return policy

    def _act(self, tensordict: TensorDictBase) -> TensorDictBase:
        with self._uncompiled():
            return self.policy(tensordict).select(*self._actor_outputs)

    def _act_with(self, exploration: ExplorationType, tensordict: TensorDictBase) -> TensorDictBase:
        with set_exploration_type(exploration):
            return self._act(tensordict)

    def update(self, data: TensorDictBase) -> dict[str, float]:
        """Value estimation once, then epochs of shuffled mini-batches of sequences."""
        config = self.config
        warmup = self.iteration < config.critic_warmup_iterations
        self._apply_schedules()
        self._train_mode(False)
        start = time.perf_counter()
        iteration = self.iteration + 1
        with distributed.watch(
            "the value estimation (all-reduce of the returns)", iteration=iteration
        ):
            with self._autocast(), self._uncompiled():
                self.algorithm.estimate(data)
            self._synchronize()
        estimation_seconds = time.perf_counter() - start
        self._train_mode(True)
        sums: dict[str, torch.Tensor] = {}
        count = 0
        with distributed.watch("the mini-batch updates (all-reduces of the gradients)"):
            for _ in range(config.epochs):
                order = torch.randperm(data.shape[0], device=self.device)
                for index in order.chunk(self.minibatches):
                    step = (len(index), warmup)  # one graph per mini-batch size and kind of step
                    if step not in self._update_steps:
                        self._update_steps[step] = self._minibatch_update(critics_only=warmup)
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
        metrics["estimation_seconds"] = estimation_seconds
        return metrics

    def _minibatch_update(self, *, critics_only: bool) -> Callable:
        """One mini-batch's update: the loss and its backward pass (:meth:`_backward`), the
        gradients averaged over the processes, the clipped AdamW step (:meth:`_step`); with
        ``critics_only``, of the critics alone (the trunk and the policy get no gradient, and
        AdamW leaves them exactly as they are).

        With CUDA graphs, where the algorithm's loss allows them, a single process replays the
        whole update as one graph. Several processes replay the backward pass and the step as
        two graphs and average between them, eagerly: a collective captured in a graph escapes
        torch's NCCL watchdog (a peer that never joins it blocks the replay for ever), and a
        capture waits, without a timeout, for every collective in flight to finish."""
        backward = functools.partial(self._backward, critics_only=critics_only)
        step = functools.partial(self._step, critics_only=critics_only)
        graphs = self._graphs and self.algorithm.capturable
        single = distributed.world_size() == 1
        if graphs and not single:
            backward, step = CudaGraphed(backward), CudaGraphed(step)

        def update(batch: TensorDictBase) -> TensorDictBase:
            out = backward(batch)
            averaged = distributed.average(out.get(_EXCHANGED))  # itself in a single process
            exchanged = TensorDict({_EXCHANGED: averaged}, device=averaged.device)
            return out.exclude(_EXCHANGED).update(step(exchanged))

        return CudaGraphed(update) if graphs and single else update

    def _backward(self, batch: TensorDictBase, *, critics_only: bool) -> TensorDictBase:
        """The loss terms and diagnostics of a mini-batch and, under ``_EXCHANGED``, what the
        processes average: the gradient of every parameter that gets one, flattened into one
        vector, followed by the KL estimate when the learning rate adapts to it."""
        with set_recurrent_mode(True), self._autocast():
            out = self.loss(batch)
        if critics_only:
            total = sum(out.get(term) for term in self.algorithm.critic_terms)
        else:
            total = sum(value for key, value in out.items() if key.startswith("loss_"))
        self.optimizer.zero_grad(set_to_none=True)
        total.backward()
        if critics_only:
            for parameter in self._policy_parameters:
                parameter.grad = None
        stepped = [p for p in self._parameters if p.grad is not None]
        self._stepped[critics_only] = stepped
        pieces = [parameter.grad.reshape(-1) for parameter in stepped]
        if self._adapts(critics_only):
            pieces.append(out.get("kl_approx").detach().float().reshape(1))
        out.set("loss_total", total)
        return out.detach().set(_EXCHANGED, torch.cat(pieces))

    def _step(self, exchanged: TensorDictBase, *, critics_only: bool) -> TensorDictBase:
        """The clipped AdamW step from a :meth:`_backward` output's averaged ``_EXCHANGED``:
        the gradients become views of it (and an adaptive learning rate follows its KL
        estimate, :meth:`_adapt_learning_rate`); returns the gradient norm before clipping."""
        stepped = self._stepped[critics_only]
        flat = exchanged.get(_EXCHANGED)
        sizes = [parameter.numel() for parameter in stepped]
        *gradients, rest = flat.split([*sizes, flat.numel() - sum(sizes)])
        for parameter, gradient in zip(stepped, gradients, strict=True):
            parameter.grad = gradient.view_as(parameter)
        if self._adapts(critics_only):
            self._adapt_learning_rate(rest[0])
        grads = [parameter.grad for parameter in stepped]
        # clip_grad_norm_ reads max_norm on the host; this keeps it a tensor
        grad_norm = torch.nn.utils.get_total_norm(grads)
        torch._foreach_mul_(grads, (self._max_grad_norm / (grad_norm + 1e-6)).clamp(max=1.0))
        self.optimizer.step()
        return TensorDict({"grad_norm": grad_norm})

    def _adapts(self, critics_only: bool) -> bool:
        """Whether a mini-batch update moves the trunk and policy's rate with the KL."""
        return self.config.lr_schedule == "adaptive" and not critics_only

    def _check_finite(self, metrics: dict[str, float]) -> None:
        """Raises ``FloatingPointError`` naming the first loss term, gradient norm or parameter
        that an update made non-finite, so that a run stops before it saves them. The metrics are
        on the host already; the parameters cost one host synchronisation per iteration."""
        for name, value in metrics.items():
            if (name.startswith("loss_") or name == "grad_norm") and not math.isfinite(value):
                raise self._non_finite(f"{name} = {value}", term=name)
        parameters = dict(self._named_parameters())
        finite = torch.stack([parameter.isfinite().all() for parameter in parameters.values()])
        if not finite.all():
            first = list(parameters)[int(finite.logical_not().nonzero()[0])]
            raise self._non_finite(f"parameter {first} holds non-finite values")

    def _non_finite(self, what: str, term: str = "") -> FloatingPointError:
        """The error for ``what`` turning non-finite, naming the settings most likely
        responsible first: the loss coefficients raised above their defaults (only the loss
        ``term``'s own where it is one of them), else the learning rates."""
        loss, defaults = self.config.loss, type(self.config.loss)()
        raised = [
            name
            for name in _TERM_SETTINGS.values()
            if hasattr(loss, name) and getattr(loss, name) > getattr(defaults, name)
        ]
        if _TERM_SETTINGS.get(term) in raised:
            raised = [_TERM_SETTINGS[term]]
        suspects = "the learning rates (train.lr_trunk_policy, train.lr_value_baseline)"
        if raised:
            weights = ", ".join(f"loss.{name} ({getattr(loss, name):g})" for name in raised)
            suspects = f"{weights}, raised above the default, or else {suspects}"
        return FloatingPointError(
            f"iteration {self.iteration + 1} made {what}; lower {suspects} first"
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
            "schedule_start": self.schedule_start,
            "train_config": asdict(self.config),
            "value_normalizer": (None if normalizer is None else normalizer.state_dict()),
            "torch_rng": torch.get_rng_state(),
            "cuda_rng": torch.cuda.get_rng_state_all() if torch.cuda.is_available() else None,
            "carry": None if self._carry is None else self._carry.to("cpu"),
        }
        for hook in self.hooks:
            state.update(hook.state_dict())
        if distributed.is_distributed():
            own = {key: state[key] for key in self._rank_keys}
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
        self.schedule_start = state["schedule_start"]
        own = distributed.rank_entries(state, self._rank_keys)
        if own is not None:
            torch.set_rng_state(own["torch_rng"])
            if own["cuda_rng"] is not None and torch.cuda.is_available():
                torch.cuda.set_rng_state_all(own["cuda_rng"])
            for hook in self.hooks:
                hook.load_state_dict({key: own[key] for key in hook.state_keys})
            carry = own["carry"]
            self._carry = None if carry is None else carry.to(self.device)
        self._prepare_optimizer()
        # an adaptive rate continues from where the checkpoint's put it
        self._lr_scales[0].fill_(float(self.optimizer.param_groups[0]["lr"]) / self._base_lrs[0])
        self._reset_graphs()  # the optimiser's state tensors are new

    def weights_state_dict(self) -> dict[str, Any]:
        """The weights that evaluation and finetuning read: ``networks`` (the networks handed
        to the trainer; TerraShift's trunk and heads hold all the actor needs),
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
        """RSL-RL's rule on the KL estimate of the mini-batch about to be stepped (averaged over
        the processes): the trunk and policy's rate moves by ``_KL_STEP`` when the KL leaves
        [target / 2, 2 target]. With CUDA graphs the rates are tensors and this runs inside the
        captured step, without a host synchronisation."""
        target = self.config.desired_kl
        step = torch.where(
            kl > 2.0 * target,
            1.0 / _KL_STEP,
            torch.where(kl < 0.5 * target, _KL_STEP, 1.0),
        )
        base = self._base_lrs[0]
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
        at = self.iteration - self.schedule_start
        factor = self.schedules["lr_factor"](at)
        self._lr_scales[1].fill_(factor)
        if self.config.lr_schedule == "linear":
            self._lr_scales[0].fill_(factor)
        self._set_learning_rates()
        # the loss's coefficients are buffers: assigning a float copies in place
        for name in ("clip_epsilon", "entropy_coeff", "clip_value"):
            setattr(self.loss, name, self.schedules[name](at))
        self._max_grad_norm.fill_(self.schedules["max_grad_norm"](at))

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
        self._evaluation_steps: dict[tuple, Callable] = {}  # by exploration type and shapes
        self._update_steps: dict[tuple[int, bool], Callable] = {}
        self._stepped: dict[bool, list[torch.nn.Parameter]] = {}

    def _autocast(self) -> contextlib.AbstractContextManager:
        if self.config.bf16 and self.device.type == "cuda":
            # cached casts of the weights are freed on exit: a graph must not keep them
            return torch.autocast("cuda", dtype=torch.bfloat16, cache_enabled=not self._graphs)
        return contextlib.nullcontext()

    def _uncompiled(self) -> contextlib.AbstractContextManager:
        """Where acting and the value-estimation pass run: eagerly under ``config.compile``, as
        each of their input shapes (collection's, evaluation's, the pass's pieces) would be a
        compilation of every network: a minute more per run on an empty cache, to save a tenth
        of an iteration (``docs/benchmarks.md``)."""
        if self.config.compile:
            return torch.compiler.set_stance("force_eager")
        return contextlib.nullcontext()

    def _synchronize(self) -> None:
        if self.device.type == "cuda":
            torch.cuda.synchronize(self.device)
