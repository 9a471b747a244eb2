"""An automatic curriculum over the scene's size: grid, agents and spheres, small to large.

Larger grids, more agents and more spheres each make learning from scratch brittle (TerraShift
paper, Section 5.2.2), while a policy that learnt a small scene transfers to a larger one. A
:class:`Curriculum` trains on a sequence of scenes from a start scene (the pretraining scene,
15 x 15 columns, 8 agents, 4 spheres, by default) to the run's target scene:

- **Stages**: ``stages`` scenes, the start and the target included. Each of grid size, agents
  and spheres is interpolated linearly between the start's and the target's and rounded half
  up; goals are the target's, at most one per sphere; every other field is the target's.
  Consecutive stages that come out equal are merged. A stage the simulator cannot hold (more
  spheres and goals than its spawn places) is refused at start-up, naming the settings.
- **Advance**: every ``eval_every`` iterations an evaluation (evaluation mode) scores the
  current stage's scene; when its goal fraction reaches ``threshold``, the next stage starts.
  The last stage is kept.
- **Mix**: from the second stage on, a fraction ``mix`` of the training environments stays on
  the earlier stages, spread evenly over them (the earliest first where they do not divide),
  so that what was learnt there is kept. One simulator holds one grid size, so each stage in
  the mix has its own batch of environments; :class:`~terrashift_rl.envs.mixed.MixedSceneEnv`
  steps them as one batch padded to the current stage's agents and spheres (the most in the
  mix: every size grows stage by stage), which the networks (attention over agents and
  objects) and MA-POCA's loss (absent agents masked out) take as they are. The agent-wise
  layers' work follows the stage: a 15 x 15 stage with 8 agents costs them a third of what it
  would padded to a 45 x 45 target's 24. Each advance builds the next stage's environments,
  which the trainer collects from in new episodes
  (:meth:`~terrashift_rl.training.trainer.OnPolicyTrainer.set_env`), capturing its graphs and,
  under ``train.compile``, compiling its update again for their shapes. With
  ``restart_schedules`` (the default) the training schedules start again at each advance
  (:meth:`~terrashift_rl.training.trainer.OnPolicyTrainer.restart_schedules`).

:meth:`Curriculum.state_dict` holds the stage and the env-steps of each advance, so a resumed
run continues at the same stage.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import torch
from torchrl.envs import Compose, EnvBase, InitTracker, TransformedEnv

from terrashift_rl.envs.mixed import MixedSceneEnv
from terrashift_rl.modules import TerraShiftNetworks
from terrashift_rl.sim import TerraShiftConfig
from terrashift_rl.training import distributed
from terrashift_rl.training.evaluation import evaluate_periodically
from terrashift_rl.training.settings import CurriculumSettings
from terrashift_rl.training.terrashift import check_scene
from terrashift_rl.training.trainer import OnPolicyTrainer, TrainerHook

__all__ = ["Curriculum", "CurriculumHook", "make_curriculum_env", "stage_scenes"]

_SIZES = ("grid_size", "num_agents", "num_objects")
"""The scene fields a curriculum grows."""


def _sizes(scene: TerraShiftConfig) -> tuple[int, int, int]:
    return tuple(getattr(scene, name) for name in _SIZES)


def stage_scenes(target: TerraShiftConfig, settings: CurriculumSettings) -> list[TerraShiftConfig]:
    """The curriculum's scenes from the start to ``target`` (the module's rule).

    Raises:
        ValueError: naming the setting, if the target is smaller than the start in grid size,
            agents or spheres, equals the start, or a stage is a scene the simulator cannot
            hold.

    Example:
        >>> scenes = stage_scenes(TerraShiftConfig.preset("large"), CurriculumSettings(stages=3))
        >>> [(s.grid_size, s.num_agents, s.num_objects, s.num_goals) for s in scenes]
        [(15, 8, 4, 4), (30, 16, 6, 6), (45, 24, 8, 8)]
    """
    start = tuple(getattr(settings, f"start_{name}") for name in _SIZES)
    end = _sizes(target)
    for name, first, last in zip(_SIZES, start, end, strict=True):
        if last < first:
            raise ValueError(
                f"env.{name} ({last}) is smaller than curriculum.start_{name} ({first}): a "
                f"curriculum only grows the scene; lower curriculum.start_{name} or use "
                "curriculum=none"
            )
    if start == end:
        raise ValueError(
            f"curriculum.start_grid_size, start_num_agents and start_num_objects {start} equal "
            "the env group's grid_size, num_agents and num_objects: there is nothing to grow; "
            "use curriculum=none"
        )
    scenes: list[TerraShiftConfig] = []
    for stage in range(settings.stages):
        t = stage / (settings.stages - 1)
        grid, agents, objects = (
            math.floor(first + t * (last - first) + 0.5)
            for first, last in zip(start, end, strict=True)
        )
        try:
            scene = target.replace(
                grid_size=grid,
                num_agents=agents,
                num_objects=objects,
                num_goals=min(target.num_goals, objects),
            )
        except ValueError as error:
            raise ValueError(
                f"curriculum stage {stage + 1} of {settings.stages} ({grid}x{grid} columns, "
                f"{agents} agents, {objects} spheres) is no scene the simulator holds: {error}; "
                "change curriculum.start_grid_size, curriculum.start_num_objects or "
                "curriculum.stages"
            ) from None
        if not scenes or _sizes(scene) != _sizes(scenes[-1]):
            scenes.append(scene)
    return scenes


class Curriculum:
    """Which stage a run is at, when it advances, and how its environments are shared out.

    Args:
        target: the run's scene (the ``env`` group's), the last stage.
        settings: the ``curriculum`` group's settings; ``kind`` is not read.

    Example:
        >>> curriculum = Curriculum(TerraShiftConfig.preset("finetune"), CurriculumSettings())
        >>> curriculum.describe()
        'stage 1/3: 15x15 columns, 8 agents, 4 spheres'
        >>> curriculum.passes(0.85)
        True
        >>> curriculum.advance(env_steps=1000)
        >>> curriculum.describe(), curriculum.allocation(num_envs=16)
        ('stage 2/3: 23x23 columns, 12 agents, 4 spheres', [(0, 4), (1, 12)])
    """

    def __init__(self, target: TerraShiftConfig, settings: CurriculumSettings) -> None:
        self.settings = settings
        self.scenes = stage_scenes(target, settings)
        self.stage = 0
        self.advances: list[int] = []
        """Env-steps at which each stage after the first started."""

    def check_training(self, *, algo: str, teacher: bool, num_envs: int) -> None:
        """Raises ``ValueError`` naming the setting that this curriculum cannot train with:
        an algorithm other than MA-POCA (the padding's absent agents would enter its loss), the
        scripted teacher (it plays one scene) or too few environments for the mix.

        Example:
            >>> curriculum = Curriculum(TerraShiftConfig.preset("large"), CurriculumSettings())
            >>> curriculum.check_training(algo="mappo", teacher=False, num_envs=64)
            Traceback (most recent call last):
            ...
            ValueError: curriculum=auto pads the early stages with absent agents, which only ...
        """
        if algo != "mapoca":
            raise ValueError(
                "curriculum=auto pads the early stages with absent agents, which only "
                f"train.algo=mapoca's loss leaves out; got train.algo={algo}"
            )
        if teacher:
            raise ValueError(
                "curriculum=auto trains on several scenes at once and the scripted teacher plays "
                "one; set loss.teacher_coeff=0"
            )
        self.allocation(num_envs, stage=len(self.scenes) - 1)

    @property
    def scene(self) -> TerraShiftConfig:
        """The current stage's scene."""
        return self.scenes[self.stage]

    @property
    def final(self) -> bool:
        """Whether the current stage is the target."""
        return self.stage == len(self.scenes) - 1

    def describe(self, *, short: bool = False) -> str:
        """``stage N/S: GxG columns, K agents, M spheres`` of the current stage; ``N/S`` if
        ``short``."""
        count = f"{self.stage + 1}/{len(self.scenes)}"
        if short:
            return count
        grid, agents, objects = _sizes(self.scene)
        return f"stage {count}: {grid}x{grid} columns, {agents} agents, {objects} spheres"

    def passes(self, goal_fraction: float) -> bool:
        """Whether an in-training evaluation's goal fraction at the current stage lets the run
        advance: it reaches the threshold and a next stage exists."""
        return not self.final and goal_fraction >= self.settings.threshold

    def advance(self, *, env_steps: int) -> None:
        """Starts the next stage at ``env_steps``."""
        if self.final:
            raise ValueError(f"the curriculum is at its last stage ({self.describe()})")
        self.stage += 1
        self.advances.append(env_steps)

    def allocation(self, num_envs: int, stage: int | None = None) -> list[tuple[int, int]]:
        """``(stage, environments)`` of every stage in the mix at ``stage`` (the current one if
        None), earliest first, the current stage last; a stage that the mix leaves no
        environment is left out.

        Raises:
            ValueError: if the mix leaves the current stage no environment.
        """
        stage = self.stage if stage is None else stage
        earlier = round(self.settings.mix * num_envs) if stage else 0
        if num_envs - earlier < 1:
            raise ValueError(
                f"train.num_envs={num_envs} with curriculum.mix={self.settings.mix} leaves no "
                "environment on the current stage; raise train.num_envs or lower curriculum.mix"
            )
        share, remainder = divmod(earlier, max(stage, 1))
        counts = [(i, share + (i < remainder)) for i in range(stage)]
        return [(i, n) for i, n in counts if n] + [(stage, num_envs - earlier)]

    def mix(self, num_envs: int) -> tuple[list[TerraShiftConfig], list[int]]:
        """The scenes of :meth:`allocation` and their environments, as
        :class:`~terrashift_rl.envs.mixed.MixedSceneEnv` takes them."""
        allocation = self.allocation(num_envs)
        return [self.scenes[i] for i, _ in allocation], [n for _, n in allocation]

    def stage_seed(self, seed: int) -> int:
        """The seed of the current stage's mix for a run seeded ``seed``: the scene in place
        ``i`` of the mix gets ``seed + stage * stages + i``, so every stage's streams differ."""
        return seed + self.stage * len(self.scenes)

    def state_dict(self) -> dict[str, Any]:
        """The stage, the env-steps of each advance and the stages' sizes."""
        return {
            "stage": self.stage,
            "advances": list(self.advances),
            "scenes": [list(_sizes(scene)) for scene in self.scenes],
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Continues at the stage of ``state``; raises ``ValueError`` if its stages differ
        from this curriculum's."""
        mine = [list(_sizes(scene)) for scene in self.scenes]
        if state["scenes"] != mine:
            raise ValueError(
                f"the checkpoint's curriculum has the stages (grid_size, num_agents, "
                f"num_objects) {state['scenes']}, these settings give {mine}; resume with the "
                "curriculum and env settings it was trained with"
            )
        self.stage = state["stage"]
        self.advances = list(state["advances"])


def make_curriculum_env(
    curriculum: Curriculum,
    networks: TerraShiftNetworks,
    *,
    num_envs: int,
    device: torch.device | str,
    seed: int,
) -> TransformedEnv:
    """The training environments of ``curriculum``'s current stage: its :meth:`~Curriculum.mix`
    in a :class:`~terrashift_rl.envs.mixed.MixedSceneEnv` padded to the stage's agents and
    spheres and seeded with :meth:`~Curriculum.stage_seed`, with the transforms the recurrent
    policy needs (``is_init`` and its state). The target is checked against the networks
    (:func:`~terrashift_rl.training.terrashift.check_scene`): every stage observes as it does."""
    check_scene(curriculum.scenes[-1], networks)
    scene = curriculum.scene
    base = MixedSceneEnv(
        *curriculum.mix(num_envs),
        num_agents=scene.num_agents,
        num_objects=scene.num_objects,
        device=device,
        seed=curriculum.stage_seed(seed),
    )
    primer = networks.make_tensordict_primer(scene.num_agents)
    return TransformedEnv(base, Compose(InitTracker(), primer))


class CurriculumHook(TrainerHook):
    """Runs a :class:`Curriculum` in an :class:`~terrashift_rl.training.trainer.OnPolicyTrainer`
    that collects from the hook's :attr:`env` (hand it and the hook to
    :func:`~terrashift_rl.training.terrashift.make_trainer`, the hook as ``scene_state``).

    Checkpoints hold the stage and the simulators of every scene in the mix, so a resumed run
    continues at the same stage in the same episodes: load the checkpoint's ``curriculum``
    entry into the curriculum (:meth:`Curriculum.load_state_dict`) before building the hook,
    so that its environments are the stage's. :meth:`after_iteration`, called by every process
    after each iteration, scores the current stage every ``eval_every`` iterations until the
    target and advances every process together when it passes the threshold; at the target it
    scores the first stage's scene every ``retention_every`` iterations.

    Args:
        curriculum: the stages and the run's place in them.
        networks: the networks that train; their actor is scored.
        make_evaluation_env: builds the evaluation environments of a scene (evaluation mode
            and its episodes and seed applied); None on a process that does not evaluate.

    Keyword Args:
        num_envs: this process's training environments.
        device: where they simulate.
        seed: their seed (:func:`make_curriculum_env`'s).
        eval_seed: the seed of every evaluation's scenes.

    Attributes:
        env: the current stage's training environments (:func:`make_curriculum_env`).
    """

    state_keys = ("curriculum", "simulator")

    def __init__(
        self,
        curriculum: Curriculum,
        networks: TerraShiftNetworks,
        make_evaluation_env: Callable[[TerraShiftConfig], EnvBase] | None,
        *,
        num_envs: int,
        device: torch.device | str,
        seed: int,
        eval_seed: int,
    ) -> None:
        self.curriculum = curriculum
        self.networks = networks
        self.make_evaluation_env = make_evaluation_env
        self.num_envs = num_envs
        self.device = device
        self.seed = seed
        self.eval_seed = eval_seed
        self._evaluation: tuple[int, EnvBase] | None = None  # (stage, its environments)
        self.env = self._make_env()

    def after_iteration(self, trainer: OnPolicyTrainer) -> dict[str, float]:
        """Every ``eval_every`` iterations before the target: scores the current stage (on the
        evaluating process) and, if that passes the threshold, starts the next stage on every
        process at once (the trainer collects from its environments in new episodes).
        Returns the metrics to log: ``curriculum_stage`` (from 1, after any advance) and the
        scores, ``curriculum_eval_goal_fraction``, ...; at the target, every
        ``retention_every`` iterations, the first stage's: ``curriculum_start_eval_...``."""
        curriculum = self.curriculum
        stage = {"curriculum_stage": float(curriculum.stage + 1)}
        if curriculum.final:
            every = curriculum.settings.retention_every
            if self.make_evaluation_env is None or every is None or trainer.iteration % every:
                return stage
            scores = self._evaluate(trainer, 0)
            return {**stage, **{f"curriculum_start_{name}": v for name, v in scores.items()}}
        if trainer.iteration % curriculum.settings.eval_every:
            return stage
        scores, passed = {}, False
        if self.make_evaluation_env is not None:
            scores = self._evaluate(trainer, curriculum.stage)
            passed = curriculum.passes(scores["eval_goal_fraction"])
        if distributed.any_process(passed, "the next curriculum stage"):
            curriculum.advance(env_steps=trainer.env_steps)
            self.env = self._make_env()
            trainer.set_env(self.env)
            if curriculum.settings.restart_schedules:
                trainer.restart_schedules()
        return {
            "curriculum_stage": float(curriculum.stage + 1),
            **{f"curriculum_{name}": value for name, value in scores.items()},
        }

    def _make_env(self) -> TransformedEnv:
        return make_curriculum_env(
            self.curriculum,
            self.networks,
            num_envs=self.num_envs,
            device=self.device,
            seed=self.seed,
        )

    def _evaluate(self, trainer: OnPolicyTrainer, stage: int) -> dict[str, float]:
        if self._evaluation is None or self._evaluation[0] != stage:
            self._evaluation = (stage, self.make_evaluation_env(self.curriculum.scenes[stage]))
        return evaluate_periodically(
            self._evaluation[1],
            self.networks.actor,
            seed=self.eval_seed,
            policies=trainer.evaluation_policy,
        )

    def state_dict(self) -> dict[str, Any]:
        return {
            "curriculum": self.curriculum.state_dict(),
            "simulator": self.env.base_env.simulator_state(),
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restores the stage and the simulators; raises ``ValueError`` if the state's stage
        is not the one this hook's environments were built for."""
        saved, built = state["curriculum"]["stage"], self.curriculum.stage
        if saved != built:
            raise ValueError(
                f"the checkpoint's curriculum is at stage {saved + 1}, these environments were "
                f"built at stage {built + 1}: load its curriculum entry into the "
                "Curriculum (Curriculum.load_state_dict) before building the CurriculumHook"
            )
        self.curriculum.load_state_dict(state["curriculum"])
        self.env.base_env.load_simulator_state(state["simulator"])
