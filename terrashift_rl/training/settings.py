"""The settings room: every setting of the recipes, typed once and checked once at start-up.

Each config group of ``recipes/configs`` is a dataclass whose fields carry their type, default,
allowed range (:func:`~terrashift_rl.fields.setting`) and a docstring:

============== ===============================================================================
group          settings
============== ===============================================================================
``env``        :class:`~terrashift_rl.sim.TerraShiftConfig` (the simulator's scene)
``model``      :class:`~terrashift_rl.modules.TerraShiftModelConfig` (network sizes)
``train``      :class:`TrainConfig` (collection, optimisation, execution)
``loss``       the algorithm's own: :class:`~terrashift_rl.training.algorithms.MAPOCAConfig`,
               :class:`~terrashift_rl.training.algorithms.MAPPOConfig` or
               :class:`~terrashift_rl.training.algorithms.IPPOConfig`, picked by the ``algo``
               group
``run``        :class:`RunConfig` (seed, length, checkpoints, evaluations)
``logger``     :class:`LoggerConfig`
``curriculum`` :class:`CurriculumSettings` (stages from a small scene to ``env``'s)
============== ===============================================================================

:class:`RecipeConfig` is the training recipes' whole config and :class:`EvaluateConfig` the
evaluation recipe's; :meth:`RecipeConfig.of` and :meth:`EvaluateConfig.of` build them from the
composed Hydra config through :func:`~terrashift_rl.fields.build`, which refuses a key that its
group lacks (also one added with ``+``), a value of the wrong type (an integer for a boolean) or
outside its range, naming the key, the value and what is allowed; then what the settings make
together: the networks' size (:func:`check_network_size`) and the reward's and the loss's range in
float32 (:func:`check_reward_range`, :func:`check_loss_range`). :func:`register_config_schemas`
gives Hydra every group's defaults, so each field can be set as ``group.field=value``;
:func:`override` writes a setting back as the command line sets it.
"""

from __future__ import annotations

import dataclasses
import json
import math
import re
import shlex
from dataclasses import dataclass, field
from typing import Any

import torch
from hydra.core.config_store import ConfigStore
from hydra.core.override_parser.overrides_parser import OverridesParser
from hydra.errors import OverrideParseException
from omegaconf import DictConfig, OmegaConf

from terrashift_rl.fields import (
    Allowed,
    above,
    at_least,
    build,
    check_fields,
    interval,
    one_of,
    setting,
)
from terrashift_rl.modules import TerraShiftModelConfig, make_terrashift_networks
from terrashift_rl.sim import TerraShiftConfig
from terrashift_rl.training.algorithms import ALGORITHMS, LossConfig, MAPOCAConfig

__all__ = [
    "CurriculumSettings",
    "EvaluateConfig",
    "LoggerConfig",
    "RecipeConfig",
    "RunConfig",
    "TrainConfig",
    "VideoConfig",
    "check_loss_range",
    "check_network_size",
    "check_reward_range",
    "hydra_override",
    "loss_config",
    "override",
    "register_config_schemas",
]

NAME = Allowed(
    lambda value: re.fullmatch(r"[\w+=-][\w.+=-]{0,99}", value, re.ASCII) is not None,
    "a name of 1 to 100 letters, digits, _ - + = or . (not first), never a path",
)
PATH = Allowed(lambda value: value != "", "a non-empty path")
DEVICE = Allowed(
    lambda value: re.fullmatch(r"auto|cpu|cuda(:\d+)?", value) is not None,
    "auto, cpu, cuda or cuda:<index>",
)
OVERRIDES = Allowed(
    lambda value: all("=" in item for item in value), "a list of overrides (key=value)"
)
SEED = Allowed(lambda value: 0 <= value < 2**64, "in [0, 2**64)")

MAX_NETWORK_PARAMETERS = 100_000_000
"""The most parameters a model's networks may hold (the paper's hold 1.9 million): 400 MB of
float32 weights, and four times that with gradients and AdamW's moments. Larger sizes are
refused before anything is allocated."""
FLOAT32_MAX = float(torch.finfo(torch.float32).max)
"""The largest finite float32, the rewards' and the losses' dtype."""


@dataclass
class TrainConfig:
    """Collection and optimisation settings of the on-policy trainer (the ``train`` group) and
    the loss's (``loss``, the algorithm's own settings class).

    Start/end pairs are linear schedules over ``schedule_iterations`` updates. The defaults
    suit thousands of environments on one GPU; Table 1's (``recipes/configs/mapoca_paper.yaml``)
    suit them poorly (docs/experiments.md).

    Example:
        >>> TrainConfig(num_envs=4, minibatches=8)  # doctest: +ELLIPSIS
        Traceback (most recent call last):
        ...
        ValueError: train.minibatches (8) exceeds train.num_envs (4): a mini-batch holds ...
    """

    num_envs: int = setting(2048, at_least(1))
    """Environments stepped together (by each process under torchrun)."""
    steps_per_iteration: int = setting(32, at_least(1))
    """Decisions collected per environment per iteration; also the GRU's training sequence."""
    epochs: int = setting(2, at_least(1))
    """Passes over each collected batch."""
    minibatches: int = setting(8, at_least(1))
    """Mini-batches per epoch, each of num_envs / minibatches whole sequences in all: under
    torchrun each of N processes splits its own batch into N x minibatches."""
    lr_trunk_policy: float = setting(1.0e-3, above(0))
    """AdamW learning rate of the trunk and the policy head at the start (3e-4 barely moves
    a Beta policy per update)."""
    lr_value_baseline: float = setting(6.0e-4, above(0))
    """AdamW learning rate of the critics at the start (MA-POCA's value and baseline heads,
    MAPPO's value head, IPPO's per-agent value head)."""
    lr_schedule: str = setting("linear", one_of("linear", "adaptive"))
    """How the trunk and policy's learning rate moves: ``linear`` from its start to
    ``lr_end_factor`` times it over ``schedule_iterations`` updates; ``adaptive`` so that the
    policy's KL divergence per update stays near ``desired_kl`` (RSL-RL's rule: after each
    mini-batch's KL estimate, divide by 1.5 above twice the target, multiply by 1.5 below half
    of it), within [lr_min, lr_max]. The critics' rate is linear either way."""
    lr_end_factor: float = setting(0.1, above(0))
    """Linear schedules end at this fraction of their learning rate's start."""
    desired_kl: float = setting(0.01, above(0))
    """With ``lr_schedule=adaptive``, the KL divergence per update the learning rates aim at."""
    lr_min: float = setting(1.0e-5, above(0))
    """With ``lr_schedule=adaptive``, the trunk and policy's smallest learning rate."""
    lr_max: float = setting(1.0e-2, above(0))
    """With ``lr_schedule=adaptive``, the trunk and policy's largest learning rate."""
    weight_decay: float = setting(0.01, at_least(0))
    """AdamW weight decay."""
    max_grad_norm_start: float = setting(5.0, above(0))
    """Gradient-norm clip of every update at the start."""
    max_grad_norm_end: float = setting(0.5, above(0))
    """Gradient-norm clip after ``schedule_iterations`` updates."""
    schedule_iterations: int = setting(1000, at_least(1))
    """Updates over which every schedule runs from start to end."""
    critic_warmup_iterations: int = setting(0, at_least(0))
    """Iterations at the start of a run that train only the critics, with the
    trunk and policy frozen: a pretrained policy then meets a new scene with critics fitted to
    it (and return statistics re-estimated) instead of advantages from miscalibrated ones."""
    bf16: bool = setting(False)
    """Run the networks under bfloat16 autocast on CUDA."""
    tf32: bool = setting(True)
    """On CUDA, let float32 matrix products use TensorFloat-32 tensor cores (sets the
    process-wide ``torch.backends.cuda.matmul.allow_tf32``)."""
    stagger_episodes: bool = setting(True)
    """Spread the first episodes' step limits over an episode's length, so that environments do
    not reset together (:meth:`~terrashift_rl.envs.terrashift.TerraShiftEnv.stagger_episodes`)."""
    compile: bool = setting(False)
    """``torch.compile`` the update's networks (not the GRU's loop over time; acting and value
    estimation run eagerly); the first iterations compile. ``train=default`` sets it."""
    cuda_graphs: bool = setting(True)
    """On CUDA, replay the actor's collection step and the mini-batch update (loss, backward,
    clipping, AdamW) as CUDA graphs (:class:`~terrashift_rl.training.graphs.CudaGraphed`);
    ignored on other devices."""
    deterministic: bool = setting(False)
    """Use only deterministic algorithms (sets the process-wide
    ``torch.use_deterministic_algorithms(True)`` and ``CUBLAS_WORKSPACE_CONFIG`` if unset), so
    that a seeded run on CUDA repeats exactly on the same machine and software; on the CPU runs
    repeat without it."""
    loss: LossConfig = field(default_factory=MAPOCAConfig)
    """The algorithm's loss settings (the ``loss`` group); its class is the algorithm."""

    def __post_init__(self) -> None:
        self.validate()

    @classmethod
    def of(cls, values: dict[str, Any], loss: dict[str, Any]) -> TrainConfig:
        """The ``train`` settings ``values`` with the ``loss`` settings of the algorithm that
        ``loss["algo"]`` names (:func:`loss_config`), every one checked."""
        return build(cls, {**values, "loss": loss_config(loss)}, "train")

    @property
    def algo(self) -> str:
        """The algorithm, a key of :data:`~terrashift_rl.training.algorithms.ALGORITHMS`."""
        return self.loss.algo

    def minibatches_per_process(self, processes: int = 1) -> int:
        """Mini-batches per epoch of each of ``processes`` data-parallel processes."""
        return processes * self.minibatches

    def validate(self, *, processes: int = 1) -> None:
        """Raises ``ValueError`` naming the first setting of the wrong type or outside its
        allowed range, or an impossible combination (with ``processes``), saying what to change."""
        check_fields(self, "train")
        self.loss.validate()
        if self.minibatches_per_process(processes) > self.num_envs:
            several = f" x {processes} processes" if processes > 1 else ""
            raise ValueError(
                f"train.minibatches ({self.minibatches}){several} exceeds train.num_envs "
                f"({self.num_envs}): a mini-batch holds whole environment sequences, so use "
                f"fewer mini-batches{several and ' or processes'} or more environments"
            )
        if self.lr_schedule == "adaptive" and not (
            self.lr_min <= self.lr_trunk_policy <= self.lr_max
        ):
            raise ValueError(
                f"train.lr_trunk_policy ({self.lr_trunk_policy}) must lie in [train.lr_min, "
                f"train.lr_max] = [{self.lr_min}, {self.lr_max}] with train.lr_schedule=adaptive"
            )


def loss_config(values: dict[str, Any]) -> LossConfig:
    """The loss settings of the algorithm ``values["algo"]`` names, from the ``loss`` group's
    ``values``; a setting of another algorithm is refused naming it and the algorithm.

    Example:
        >>> loss_config({"algo": "mappo", "teacher_coeff": 1.0})  # doctest: +ELLIPSIS
        Traceback (most recent call last):
        ...
        ValueError: loss.teacher_coeff is not a setting of algo=mappo; its loss settings are: ...
    """
    values = dict(values)
    algo = values.pop("algo", None)
    if algo not in ALGORITHMS:
        raise ValueError(f"loss.algo must be one of {', '.join(ALGORITHMS)}, got {algo!r}")
    known = [field.name for field in dataclasses.fields(ALGORITHMS[algo])]
    unknown = [key for key in values if key not in known]
    if unknown:
        raise ValueError(
            f"loss.{unknown[0]} is not a setting of algo={algo}; its loss settings are: "
            + ", ".join(known)
        )
    return build(ALGORITHMS[algo], values, "loss")


@dataclass
class RunConfig:
    """What a training run does around the loop (the ``run`` settings)."""

    name: str = setting("mapoca_pretrain", NAME)
    """The run's name: the progress bar's label and the logger's run name (a csv or
    tensorboard logger's folder under ``<run>/logs``, so a name, never a path)."""
    seed: int = setting(0, SEED)
    """Seed of the networks' initialisation and the training environments (rank r of a
    data-parallel run: seed + r)."""
    device: str = setting("auto", DEVICE)
    """``auto`` (CUDA when present, else the CPU with ``cpu_defaults``), ``cpu``, ``cuda`` or
    ``cuda:<index>``."""
    cpu_defaults: list[str] = setting(
        [
            "model=small",
            "train.num_envs=32",
            "train.steps_per_iteration=32",
            "train.compile=false",
            "run.eval_episodes=16",
            "run.minutes=5",
            "run.threads=1",
        ],
        OVERRIDES,
    )
    """With ``device=auto`` and no CUDA device, these overrides size the run for a CPU (first
    iteration in seconds, uncompiled, under 1 GB, five minutes, one thread), each unless the
    command line sets its key or group; a run from a checkpoint (resume, pretrained) builds that
    checkpoint's model instead of ``model=small``. ``device=cpu`` keeps the configured sizes."""
    threads: int | None = setting(None, at_least(1), null="torch's default")
    """Threads of torch's operators on the CPU (``torch.set_num_threads``). The CPU-sized run
    takes one: its networks are too small to share out, and on cores that other programs use
    too, threads that wait for each other made a policy step 30 times slower."""
    total_env_steps: int = setting(100_000_000, at_least(1))
    """Environment steps (decisions x environments) after which the run stops."""
    minutes: float | None = setting(None, above(0), null="no time limit")
    """Wall-clock minutes after which the run stops with a checkpoint."""
    checkpoint_every: int = setting(25, at_least(1))
    """Iterations between writes of ``checkpoints/last.pt``."""
    best_window: int = setting(8, at_least(0))
    """``best.pt`` holds the weights at the best mean reward over this many iterations; 0
    writes none."""
    snapshot_every: int | None = setting(None, at_least(1), null="no snapshots")
    """Also keep the weights every n iterations (``iteration_NNNNNN.pt``)."""
    eval_every: int | None = setting(50, at_least(1), null="no evaluation")
    """Iterations between evaluations in evaluation mode (no respawn, mean action), logged as
    ``eval_goal_fraction``, ...; also before the first with ``pretrained`` (the pretrained
    weights' zero-shot score)."""
    eval_episodes: int = setting(128, at_least(1))
    """Episodes per evaluation (one environment each)."""
    eval_seed: int = setting(1, SEED)
    """Seed of every evaluation's scenes (training uses ``seed``)."""
    eval_sampled: bool = setting(False)
    """Also score the sampled actions on those scenes (``eval_sampled_...``)."""
    resume: str | None = setting(None, PATH, null="a fresh start")
    """A checkpoint of this recipe to continue from, exactly."""
    pretrained: str | None = setting(None, PATH, null="no pretrained weights")
    """A checkpoint whose network weights start this run (finetuning)."""
    collective_timeout_s: float = setting(300.0, above(0))
    """Under ``torchrun``: seconds a rank may wait for the others in one exchange before it
    ends the run with a message naming itself, the iteration and the exchange (one of them
    stopped answering or died)."""


@dataclass
class LoggerConfig:
    """Where the metrics go (the ``logger`` group)."""

    kind: str = setting("none", one_of("wandb", "csv", "tensorboard", "none"))
    """``wandb``, ``csv`` or ``tensorboard`` files under the run's folder, or ``none``."""
    mode: str = setting("offline", one_of("offline", "online"))
    """With ``kind=wandb``: ``offline`` (no account, no network) or ``online`` (syncs)."""
    project: str = setting("terrashift_rl", NAME)
    """With ``kind=wandb``: the project's name."""


@dataclass
class CurriculumSettings:
    """The ``curriculum`` group: whether and how the scene grows during training.

    Example:
        >>> CurriculumSettings(kind="auto", mix=1.0)
        Traceback (most recent call last):
        ...
        ValueError: curriculum.mix must be a finite number in [0, 1), got 1.0
    """

    kind: str = setting("none", one_of("none", "auto"))
    """``none``: the ``env`` group's scene from the start; ``auto``: stages up to it."""
    stages: int = setting(3, at_least(2))
    """Scenes from the start to the target, both included (``env=large``: 15/30/45 columns)."""
    start_grid_size: int = setting(15, at_least(2))
    """Columns per side of the first stage's grid."""
    start_num_agents: int = setting(8, at_least(1))
    """Wave agents of the first stage."""
    start_num_objects: int = setting(4, at_least(1))
    """Spheres of the first stage."""
    threshold: float = setting(0.8, interval(0, 1))
    """Goal fraction of an in-training evaluation at the current stage at which the next
    stage starts; 0 advances at every evaluation (``eval_every`` iterations per stage)."""
    eval_every: int = setting(10, at_least(1))
    """Iterations between the evaluations of the current stage that decide an advance
    (evaluation mode, ``run.eval_episodes`` episodes of ``run.eval_seed``'s scenes); none once
    the target is reached (``run.eval_every`` scores the target throughout)."""
    retention_every: int | None = setting(50, at_least(1), null="never")
    """Iterations between evaluations of the first stage's scene once the target is reached,
    logged as ``curriculum_start_eval_*``: what the run keeps of where it started."""
    mix: float = setting(0.25, interval(0, 1, high_open=True))
    """Fraction of the training environments kept on earlier stages once there are any,
    spread evenly over them."""
    restart_schedules: bool = setting(True)
    """Whether each advance starts the training schedules again (else they run once)."""

    def __post_init__(self) -> None:
        check_fields(self, "curriculum")


@dataclass
class RecipeConfig:
    """The training recipes' whole config: the scene, the networks, training with its loss, the
    run, the logger and the curriculum."""

    env: TerraShiftConfig = field(default_factory=TerraShiftConfig)
    """The scene the policy trains on."""
    model: TerraShiftModelConfig = field(default_factory=TerraShiftModelConfig)
    """Network sizes."""
    train: TrainConfig = field(default_factory=TrainConfig)
    """Collection, optimisation and the loss."""
    run: RunConfig = field(default_factory=RunConfig)
    """Seed, length, device, checkpoints and evaluations."""
    logger: LoggerConfig = field(default_factory=LoggerConfig)
    """Where the metrics go."""
    curriculum: CurriculumSettings = field(default_factory=CurriculumSettings)
    """Whether and how the scene grows from a small one to ``env``'s during training."""

    @classmethod
    def of(cls, cfg: DictConfig) -> RecipeConfig:
        """The settings the composed config ``cfg`` holds, every one checked (the ``loss`` group
        goes into :attr:`TrainConfig.loss`)."""
        values = OmegaConf.to_container(cfg, resolve=True)
        groups = [*(field.name for field in dataclasses.fields(cls)), "loss"]
        unknown = [key for key in values if key not in groups]
        if unknown:
            raise ValueError(
                f"{unknown[0]} is not a setting; the config groups are: {', '.join(groups)}"
            )
        loss = values.pop("loss", {"algo": "mapoca"})
        values["train"] = TrainConfig.of(values.get("train", {}), loss)
        return build(cls, values, "")

    def __post_init__(self) -> None:
        check_network_size(self.model)
        check_reward_range(self.env)
        check_loss_range(self.train, self.env)


@dataclass
class VideoConfig:
    """The evaluation recipe's video of one environment."""

    steps: int = setting(256, at_least(0))
    """Decisions to record; 0 records no video."""
    every: int = setting(2, at_least(1))
    """Render every n-th decision."""
    fps: float = setting(15.0, above(0))
    """Frames per second of the video."""
    format: str = setting("mp4", one_of("mp4", "gif"))
    """The video's file format."""


@dataclass
class EvaluateConfig:
    """The evaluation recipe's config (``recipes/configs/evaluate.yaml``)."""

    env: TerraShiftConfig = field(default_factory=TerraShiftConfig)
    """The scene, unless ``scene_from_checkpoint`` takes the checkpoint's."""
    checkpoint: str | None = setting(None, PATH, null="the baselines alone")
    """A training checkpoint to score."""
    scene_from_checkpoint: bool = setting(True)
    """Evaluate on the checkpoint's scene rather than the ``env`` group's."""
    episodes: int = setting(256, at_least(1))
    """Episodes scored, one per environment."""
    respawn: bool = setting(False)
    """``false``: evaluation mode; ``true``: training mode (respawn; every episode runs to the
    step limit), the paper's reward per decision."""
    baselines: bool = setting(True)
    """Also score random, zero and the scripted heuristic."""
    device: str = setting("auto", DEVICE)
    """``auto`` (CUDA when present, else the CPU with ``cpu_defaults``), ``cpu``, ``cuda`` or
    ``cuda:<index>``."""
    cpu_defaults: list[str] = setting(
        ["episodes=16", "video.steps=128", "video.every=4", "threads=1"], OVERRIDES
    )
    """With ``device=auto`` and no CUDA device, these overrides apply unless the command line
    sets their keys: under a minute on two CPU cores (25–38 s, `benchmarks/first_hour.py`)."""
    threads: int | None = setting(None, at_least(1), null="torch's default")
    """Threads of torch's operators on the CPU, as the training run's ``run.threads``."""
    seed: int = setting(1, SEED)
    """Seed of the scenes and the sampled actions."""
    video: VideoConfig = field(default_factory=VideoConfig)
    """The video of one environment."""
    wandb: bool = setting(False)
    """Also log the metrics and the video to an offline wandb run."""

    def __post_init__(self) -> None:
        check_reward_range(self.env)

    @classmethod
    def of(cls, cfg: DictConfig) -> EvaluateConfig:
        """The settings the composed config ``cfg`` holds, every one checked."""
        return build(cls, OmegaConf.to_container(cfg, resolve=True), "")


# --- what the settings make together ------------------------------------------------------------
def check_network_size(model: TerraShiftModelConfig, key: str = "model") -> None:
    """Raises ``ValueError`` naming the settings ``key`` when the networks of ``model`` would
    hold more than :data:`MAX_NETWORK_PARAMETERS` parameters; they are counted on PyTorch's
    meta device, which allocates nothing."""
    try:
        with torch.device("meta"):
            count = sum(p.numel() for p in make_terrashift_networks(model).parameters())
    except (RuntimeError, OverflowError, MemoryError) as error:  # sizes past PyTorch's indices
        raise ValueError(f"{key}: the networks of these sizes cannot be built ({error})") from None
    if count > MAX_NETWORK_PARAMETERS:
        raise ValueError(
            f"{key}: the networks would hold {count:.3g} parameters, more than the "
            f"{MAX_NETWORK_PARAMETERS:,} that fit a GPU's memory with their gradients and "
            f"optimiser state; lower {key}.embed_dim ({model.embed_dim}), {key}.ffn_dim "
            f"({model.ffn_dim}) or {key}.trunk_layers ({model.trunk_layers})"
        )


def reward_bound(env: TerraShiftConfig) -> dict[str, float]:
    """An upper bound of a decision's reward magnitude, as the sum of each reward setting's
    share (the terms of :data:`~terrashift_rl.sim.config.REWARD_TERMS`, every one at its
    largest on every tick of the decision, divided by ``reward_normalizer``).

    Example:
        >>> share = reward_bound(TerraShiftConfig())
        >>> max(share, key=share.get), f"{sum(share.values()):.0f}"
        ('distance_scale', '225')
    """
    reach = 2.0 * math.sqrt(2.0) * env.out_of_bounds_xy + env.out_of_bounds_z  # any distance
    per_sphere = {
        "goal_reward": abs(env.goal_reward),
        "out_of_bounds_penalty": abs(env.out_of_bounds_penalty),
        "distance_scale": env.distance_scale * env.distance_clip,
        "potential_scale": abs(env.potential_scale) * reach * (1.0 + env.potential_gamma),
        "slow_penalty": abs(env.slow_penalty),
        "alignment_scale": abs(env.alignment_scale),
        "sphere_approach_scale": abs(env.sphere_approach_scale) * reach,
    }
    share = {name: env.num_objects * value for name, value in per_sphere.items()}
    share["approach_scale"] = env.num_agents * abs(env.approach_scale) * reach
    share["time_penalty"] = abs(env.time_penalty)
    ticks = env.action_repeat / env.reward_normalizer
    return {name: value * ticks for name, value in share.items()}


def check_reward_range(env: TerraShiftConfig, key: str = "env") -> None:
    """Raises ``ValueError`` naming the settings of ``key`` that can make a decision's reward
    infinite in float32 (:func:`reward_bound` beyond :data:`FLOAT32_MAX`), or that float32 holds
    as infinity or zero.

    Example:
        >>> check_reward_range(TerraShiftConfig(reward_normalizer=1e-300))  # doctest: +ELLIPSIS
        Traceback (most recent call last):
        ...
        ValueError: env.reward_normalizer (1e-300) is 0 in float32, the reward's dtype; ...
    """
    if env.reward_normalizer < torch.finfo(torch.float32).tiny:
        raise ValueError(
            f"{key}.reward_normalizer ({env.reward_normalizer:g}) is 0 in float32, the reward's "
            "dtype; every reward would be infinite: use a normalizer >= 1e-30"
        )
    share = reward_bound(env)
    largest = max(share, key=share.get)
    if sum(share.values()) > FLOAT32_MAX:
        raise ValueError(
            f"{key}.{largest} ({getattr(env, largest):g}) with {key}.reward_normalizer "
            f"({env.reward_normalizer:g}) makes a decision's reward reach "
            f"{sum(share.values()):.3g}, beyond float32's largest number ({FLOAT32_MAX:.3g}): "
            f"the reward would be infinite; lower {key}.{largest} or raise the normalizer"
        )


def check_loss_range(train: TrainConfig, env: TerraShiftConfig) -> None:
    """Raises ``ValueError`` naming the loss coefficient (``loss.*_coeff*``) that can make the
    loss infinite in float32: times the largest squared return (a decision's
    :func:`reward_bound` over ``1 / (1 - gamma)`` decisions, or an episode's with
    ``gamma = 1``), beyond :data:`FLOAT32_MAX`."""
    loss = train.loss
    horizon = env.max_episode_steps if loss.gamma == 1 else 1 / (1 - loss.gamma)
    squared_return = (sum(reward_bound(env).values()) * horizon) ** 2
    for name in (entry.name for entry in dataclasses.fields(loss) if "_coeff" in entry.name):
        value = getattr(loss, name)
        if value * squared_return > FLOAT32_MAX:
            raise ValueError(
                f"loss.{name} ({value:g}) times the largest squared return "
                f"({squared_return:.3g}) goes beyond float32's largest number "
                f"({FLOAT32_MAX:.3g}): the loss would be infinite; lower loss.{name}"
            )


def register_config_schemas() -> None:
    """Gives Hydra the defaults of every group, as plain values: the group files name the fields
    they change, the settings classes supply the others, so every field can be set as
    ``group.field=value``, and :meth:`RecipeConfig.of` types them. Options: ``env/schema``,
    ``model/schema`` and ``model/schema_small``
    (:meth:`~terrashift_rl.modules.TerraShiftModelConfig.small`), ``train/schema``,
    ``algo/<algo>_schema`` (placed at ``loss``, with ``loss.algo``), ``logger/schema``,
    ``curriculum/schema``, ``run_schema`` (placed at ``run``) and ``evaluate_schema``."""
    store = ConfigStore.instance()
    store.store(group="env", name="schema", node=dataclasses.asdict(TerraShiftConfig()))
    store.store(group="model", name="schema", node=dataclasses.asdict(TerraShiftModelConfig()))
    store.store(
        group="model", name="schema_small", node=dataclasses.asdict(TerraShiftModelConfig.small())
    )
    train = dataclasses.asdict(TrainConfig())
    del train["loss"]
    store.store(group="train", name="schema", node=train)
    for algo, config in ALGORITHMS.items():
        node = {"algo": algo, **dataclasses.asdict(config())}
        store.store(group="algo", name=f"{algo}_schema", node=node, package="loss")
    store.store(group="logger", name="schema", node=dataclasses.asdict(LoggerConfig()))
    store.store(group="curriculum", name="schema", node=dataclasses.asdict(CurriculumSettings()))
    store.store(name="run_schema", node=dataclasses.asdict(RunConfig()), package="run")
    evaluate = dataclasses.asdict(EvaluateConfig())
    del evaluate["env"]
    store.store(name="evaluate_schema", node=evaluate)


def hydra_override(key: str, value: Any) -> str:
    """``key=value`` as Hydra reads it back as ``value``.

    Example:
        >>> print(hydra_override("env.column_shape", "box"), hydra_override("model.gain", 0.5))
        env.column_shape=box model.gain=0.5
    """
    text = json.dumps(value, separators=(",", ":"))  # null, true, [4,8,8], "box"
    if isinstance(value, str):
        try:  # unquoted where Hydra reads the bare string as that string
            if OverridesParser.create().parse_override(f"{key}={value}").value() == value:
                text = value
        except OverrideParseException:
            pass
    return f"{key}={text}"


def override(key: str, value: Any) -> str:
    """:func:`hydra_override`, quoted for a shell where needed.

    Example:
        >>> print(override("env.column_shape", "box"), override("model.cnn_channels", [8, 16]))
        env.column_shape=box 'model.cnn_channels=[8,16]'
    """
    return shlex.quote(hydra_override(key, value))
