"""TerraShift's side of training: the environment the policy needs, the trainer's parts, and the
hooks that :class:`~terrashift_rl.training.trainer.OnPolicyTrainer` calls for the scene.

:func:`make_trainer` builds the trainer from TerraShift's networks and a
:class:`~terrashift_rl.training.settings.TrainConfig`: the algorithm its loss settings build
(``algo``), AdamW over the policy's and the critics' parameters, and the hooks
:func:`terrashift_hooks` lists:

- :class:`ActionCheck`: refuses non-finite actions once per iteration
  (:meth:`~terrashift_rl.envs.terrashift.TerraShiftEnv.check_actions`);
- :class:`StaggeredEpisodes`: after the first reset, spreads the episodes' step limits
  (``train.stagger_episodes``);
- :class:`ScriptedTeacher`: the scripted heuristic's action beside the policy's on every collected
  step, and the loss's teacher weight along its schedule (``loss.teacher_coeff``);
- :class:`SimulatorState`: the simulator's state in checkpoints, so that a resumed run
  continues exactly;
- :class:`SceneMetrics`: the episode, concentration and action metrics of every iteration.
"""

from __future__ import annotations

import math
from typing import Any

import torch
from tensordict import TensorDictBase
from torchrl.envs import Compose, InitTracker, TransformedEnv

from terrashift_rl.envs import TerraShiftEnv
from terrashift_rl.envs.baselines import ScriptedHeuristicPolicy
from terrashift_rl.modules import TerraShiftNetworks, keys
from terrashift_rl.objectives import MAPOCALoss
from terrashift_rl.sim import TerraShiftConfig
from terrashift_rl.sim.types import ACTION_NAMES
from terrashift_rl.training.algorithms import Algorithm, MAPOCAConfig
from terrashift_rl.training.schedules import LinearSchedule
from terrashift_rl.training.settings import TrainConfig
from terrashift_rl.training.trainer import OnPolicyTrainer, TrainerHook

__all__ = [
    "COMPILE_OPTIONS",
    "ActionCheck",
    "SceneMetrics",
    "ScriptedTeacher",
    "SimulatorState",
    "StaggeredEpisodes",
    "action_medians",
    "check_scene",
    "concentration_metrics",
    "episode_metrics",
    "make_trainer",
    "make_training_env",
    "terrashift_hooks",
]

COMPILE_OPTIONS: dict[str, Any] = {"post_grad_fusion_options": {"decompose_mm_pass": {}}}
"""Inductor options of ``train.compile``: batched matrix products whose batch is large and whose
other sizes are small (the attention over sets of 4 to 16 tokens) become fused multiply-and-sum
kernels instead of cuBLAS batched products in tiles mostly empty (on CUDA only; Inductor's
``decompose_mm_pass`` and its thresholds)."""


def check_scene(env_config: TerraShiftConfig, networks: TerraShiftNetworks) -> None:
    """Refuses a scene that lacks an observation the networks read (the camera, the objects, the
    critics' privileged objects), or renders a camera or hands out privileged objects they do
    not read, naming the settings."""
    model = networks.config
    if model is not None:
        if bool(model.camera_channels) != bool(env_config.camera_resolution):
            raise ValueError(
                f"model.camera_channels={model.camera_channels} but env.camera_resolution="
                f"{env_config.camera_resolution}: the networks read a camera exactly when the "
                "scene renders one (camera_channels=1 with camera_resolution > 0, or both 0)"
            )
        if model.object_tokens and not env_config.observe_objects:
            raise ValueError(
                "model.object_tokens=true reads the object sequence, which env.observe_objects="
                "false leaves out: set model.object_tokens=false"
            )
        if model.critic_objects != env_config.privileged_objects:
            raise ValueError(
                f"model.critic_objects={str(model.critic_objects).lower()} but "
                f"env.privileged_objects={str(env_config.privileged_objects).lower()}: the "
                "critics read privileged objects exactly when the scene hands them out (both "
                "true, with env.observe_objects=false and model.object_tokens=false, or both "
                "false)"
            )


def make_training_env(
    env_config: TerraShiftConfig,
    networks: TerraShiftNetworks,
    *,
    num_envs: int,
    device: torch.device,
    seed: int,
) -> TransformedEnv:
    """TerraShift with the transforms the recurrent policy needs: ``is_init`` and its state;
    the scene checked against the networks first (:func:`check_scene`)."""
    check_scene(env_config, networks)
    base = TerraShiftEnv(env_config, num_envs=num_envs, device=device, seed=seed)
    primer = networks.make_tensordict_primer(env_config.num_agents)
    return TransformedEnv(base, Compose(InitTracker(), primer))


def make_trainer(
    env: TransformedEnv,
    networks: TerraShiftNetworks,
    config: TrainConfig,
    *,
    scene_state: TrainerHook | None = None,
) -> OnPolicyTrainer:
    """The trainer of ``networks`` on ``env`` (from :func:`make_training_env`) with the
    algorithm ``config.loss`` builds, AdamW over the trunk and policy head (at
    ``lr_trunk_policy``) and the algorithm's critics (at ``lr_value_baseline``), and
    :func:`terrashift_hooks`; ``scene_state`` holds the environments' state in checkpoints
    (:class:`SimulatorState` if None; a curriculum's
    :class:`~terrashift_rl.training.curriculum.CurriculumHook`)."""
    config.validate()
    teacher_coeff = getattr(config.loss, "teacher_coeff", 0.0)  # MA-POCA's alone
    scene = env.base_env.config if teacher_coeff else None  # a curriculum has no teacher
    if scene is not None and not (scene.observe_objects or scene.privileged_objects):
        raise ValueError(
            f"loss.teacher_coeff={teacher_coeff}: the teacher reads the object sequence, which "
            "env.observe_objects=false leaves out; set env.privileged_objects=true (with "
            "model.critic_objects=true) to hand it to the teacher and the critics alone"
        )
    # The estimation pass runs without gradients, so it keeps no activations for a backward
    # pass: per env-step it needs about a fifth of a mini-batch update's memory (the medium
    # network's tensors at their peak: 112 against 550 MB per 1,000 env-steps). In pieces of
    # four mini-batches it stays below an update's peak, in a few large pieces, which its
    # launches (it runs eagerly) favour.
    max_batch = min(config.num_envs, 4 * math.ceil(config.num_envs / config.minibatches))
    algorithm = config.loss.make(networks, max_batch=max_batch)
    if config.compile:  # static shapes: a curriculum's stages each compile their own
        networks.compile_networks(dynamic=False, options=COMPILE_OPTIONS)
        for head in algorithm.networks.values():
            head.module.compile(dynamic=False, options=COMPILE_OPTIONS)
    policy_parameters = [*networks.trunk.parameters(), *networks.policy_head.parameters()]
    critic_parameters = [p for critic in algorithm.critics for p in critic.parameters()]
    optimizer = torch.optim.AdamW(
        [
            {"params": policy_parameters, "lr": config.lr_trunk_policy},
            {"params": critic_parameters, "lr": config.lr_value_baseline},
        ],
        weight_decay=config.weight_decay,
    )
    return OnPolicyTrainer(
        env,
        networks.actor,
        algorithm,
        optimizer,
        config,
        networks=networks,
        hooks=terrashift_hooks(env.base_env, algorithm, config, scene_state=scene_state),
    )


def terrashift_hooks(
    env: TerraShiftEnv,
    algorithm: Algorithm,
    config: TrainConfig,
    *,
    scene_state: TrainerHook | None = None,
) -> list[TrainerHook]:
    """The hooks a TerraShift trainer runs with ``config``, in the order they are called;
    ``scene_state`` (:class:`SimulatorState` if None) holds the environments' state."""
    hooks: list[TrainerHook] = [ActionCheck()]  # before anything reads the batch
    if config.stagger_episodes:
        hooks.append(StaggeredEpisodes())
    loss = config.loss
    if isinstance(loss, MAPOCAConfig) and loss.teacher_coeff:  # MA-POCA's alone
        schedule = LinearSchedule(
            loss.teacher_coeff, loss.teacher_coeff_end, loss.teacher_iterations
        )
        hooks.append(ScriptedTeacher(env.config, algorithm.loss, schedule))
    return [*hooks, scene_state or SimulatorState(env), SceneMetrics()]


class StaggeredEpisodes(TrainerHook):
    """Spreads the first episodes' step limits over an episode's length after each reset of
    every environment (:meth:`~terrashift_rl.envs.terrashift.TerraShiftEnv.stagger_episodes`
    of ``trainer.env.base_env``), so that the environments do not all reset at the same
    decision."""

    def on_reset(self, trainer: OnPolicyTrainer, tensordict: TensorDictBase) -> None:
        trainer.env.base_env.stagger_episodes()


class ScriptedTeacher(TrainerHook):
    """Writes the scripted heuristic's action
    (:class:`~terrashift_rl.envs.baselines.ScriptedHeuristicPolicy`) into every collected step,
    under the loss's ``teacher_action`` key, and sets the loss's ``teacher_coeff`` to
    ``schedule(iteration)`` before each update; logs it as ``teacher_coeff``. The heuristic
    reads the object sequence the agents observe or, where they sort from images alone, the
    critics' privileged copy (``TerraShiftConfig.privileged_objects``)."""

    def __init__(self, scene: TerraShiftConfig, loss: MAPOCALoss, schedule: LinearSchedule):
        self.policy = ScriptedHeuristicPolicy(scene)
        self.loss = loss
        self.schedule = schedule

    def on_batch_collected(self, trainer: OnPolicyTrainer, data: TensorDictBase) -> None:
        # the coefficient is a buffer: assigning a float copies in place (for CUDA graphs)
        self.loss.teacher_coeff = self.schedule(trainer.iteration)
        observed = data.select(
            keys.AGENT_OBSERVATION, keys.OBJECTS, keys.OBJECTS_MASK, strict=False
        )
        if keys.OBJECTS not in observed.keys(include_nested=True):  # images alone: the critics'
            observed[keys.OBJECTS] = data.get(keys.PRIVILEGED_OBJECTS)
            observed[keys.OBJECTS_MASK] = data.get(keys.PRIVILEGED_OBJECTS_MASK)
        data.set(self.loss.tensor_keys.teacher_action, self.policy(observed).get(keys.ACTION))

    def metrics(self, trainer: OnPolicyTrainer, data: TensorDictBase) -> dict[str, float]:
        return {"teacher_coeff": float(self.loss.teacher_coeff)}


class ActionCheck(TrainerHook):
    """Raises the environment's ``ValueError`` once per iteration if the policy acted with NaN
    or infinity during the collection
    (:meth:`~terrashift_rl.envs.terrashift.TerraShiftEnv.check_actions` of
    ``trainer.env.base_env``): one host synchronisation per iteration instead of one per step."""

    def on_batch_collected(self, trainer: OnPolicyTrainer, data: TensorDictBase) -> None:
        trainer.env.base_env.check_actions()


class SimulatorState(TrainerHook):
    """The simulator's state in checkpoints, under ``simulator`` (on the CPU): a resumed run
    continues the very episodes the checkpoint's was playing."""

    state_keys = ("simulator",)

    def __init__(self, env: TerraShiftEnv):
        self.env = env

    def state_dict(self) -> dict[str, Any]:
        state = self.env.sim.state_dict()
        return {"simulator": {name: value.cpu() for name, value in state.items()}}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        device = self.env.device
        self.env.sim.load_state_dict(
            {name: value.to(device) for name, value in state["simulator"].items()}
        )


class SceneMetrics(TrainerHook):
    """:func:`episode_metrics`, :func:`concentration_metrics` and :func:`action_medians` of each
    collected batch; ``episodes`` adds up over the processes of a data-parallel run."""

    summed_metrics = ("episodes",)

    def metrics(self, trainer: OnPolicyTrainer, data: TensorDictBase) -> dict[str, float]:
        return {**episode_metrics(data), **concentration_metrics(data), **action_medians(data)}


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
