"""The curriculum's stages, advance, mix of stages, exact resume and refusals; the mixed env."""

from __future__ import annotations

import dataclasses
import itertools
from types import SimpleNamespace

import pytest
import torch
from torchrl.envs import Compose, InitTracker, TransformedEnv
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.modules import set_recurrent_mode

from terrashift_rl.envs import TerraShiftEnv
from terrashift_rl.envs.mixed import MixedSceneEnv
from terrashift_rl.modules import TerraShiftModelConfig, make_terrashift_networks
from terrashift_rl.objectives import ValueNormalizer
from terrashift_rl.sim import TerraShiftConfig
from terrashift_rl.training import curriculum as curriculum_module
from terrashift_rl.training.algorithms import MAPOCAConfig
from terrashift_rl.training.curriculum import (
    Curriculum,
    CurriculumHook,
    make_curriculum_env,
    stage_scenes,
)
from terrashift_rl.training.settings import CurriculumSettings, TrainConfig
from terrashift_rl.training.terrashift import make_trainer


def sizes(scenes):
    return [(s.grid_size, s.num_agents, s.num_objects, s.num_goals) for s in scenes]


# --- stages --------------------------------------------------------------------------------


def test_stages_interpolate_each_size_from_the_start_to_the_target():
    large = TerraShiftConfig.preset("large", approach_scale=0.3)
    scenes = stage_scenes(large, CurriculumSettings(stages=5))
    assert sizes(scenes) == [
        (15, 8, 4, 4),
        (23, 12, 5, 5),  # 22.5 -> 23, rounded half up
        (30, 16, 6, 6),
        (38, 20, 7, 7),
        (45, 24, 8, 8),
    ]
    # every other field is the target's
    assert {(s.approach_scale, s.time_penalty) for s in scenes} == {(0.3, 0.0)}


def test_equal_consecutive_stages_are_merged_and_goals_follow_the_target():
    target = TerraShiftConfig(grid_size=17, num_agents=8, num_objects=4, num_goals=2)
    scenes = stage_scenes(target, CurriculumSettings(stages=4))
    assert sizes(scenes) == [(15, 8, 4, 2), (16, 8, 4, 2), (17, 8, 4, 2)]


# --- advance -------------------------------------------------------------------------------


def test_a_stage_advances_when_an_evaluation_reaches_the_threshold_and_not_before():
    curriculum = Curriculum(TerraShiftConfig.preset("large"), CurriculumSettings(threshold=0.7))
    assert not curriculum.passes(0.69)
    assert curriculum.passes(0.7)
    curriculum.advance(env_steps=200)
    assert curriculum.scene.grid_size == 30
    assert curriculum.passes(0.95)
    curriculum.advance(env_steps=300)
    assert curriculum.final and curriculum.scene == TerraShiftConfig.preset("large")
    assert not curriculum.passes(1.0)  # the target is kept
    with pytest.raises(ValueError, match="at its last stage"):
        curriculum.advance(env_steps=400)
    assert (curriculum.stage, curriculum.advances) == (2, [200, 300])
    assert curriculum.describe() == "stage 3/3: 45x45 columns, 24 agents, 8 spheres"
    # threshold 0: every evaluation advances (eval_every iterations per stage)
    assert Curriculum(curriculum.scene, CurriculumSettings(threshold=0.0)).passes(0.0)


def test_the_hook_scores_the_current_stage_then_at_the_target_the_first_stage(monkeypatch):
    scored = []  # the scenes evaluated (the evaluation "env" below is its scene)

    def evaluate(env, actor, **kwargs):
        scored.append(env)
        return {"eval_goal_fraction": 0.5}

    monkeypatch.setattr(curriculum_module, "evaluate_periodically", evaluate)
    settings = CurriculumSettings(eval_every=2, retention_every=3)
    curriculum = Curriculum(TerraShiftConfig.preset("large"), settings)
    networks = make_terrashift_networks(TerraShiftModelConfig.small())
    hook = CurriculumHook(
        curriculum, networks, lambda scene: scene, num_envs=4, device="cpu", seed=0, eval_seed=1
    )
    trainer = SimpleNamespace(evaluation_policy=None)

    def after(iteration):
        trainer.iteration = iteration
        return hook.after_iteration(trainer)

    assert after(1) == {"curriculum_stage": 1.0}
    assert after(2) == {"curriculum_stage": 1.0, "curriculum_eval_goal_fraction": 0.5}
    assert scored == [curriculum.scenes[0]] and curriculum.stage == 0  # 0.5 < 0.8: no advance
    curriculum.advance(env_steps=100)
    curriculum.advance(env_steps=200)
    assert [after(i) for i in (4, 5)] == [{"curriculum_stage": 3.0}] * 2
    # at the target, every 3 iterations: the first stage's scene, not the target's
    assert after(6) == {"curriculum_stage": 3.0, "curriculum_start_eval_goal_fraction": 0.5}
    assert scored == [curriculum.scenes[0]] * 2 and scored[-1].grid_size == 15
    curriculum.settings = dataclasses.replace(settings, retention_every=None)
    assert after(9) == {"curriculum_stage": 3.0} and len(scored) == 2


# --- mix -----------------------------------------------------------------------------------


def test_the_mix_keeps_its_fraction_of_environments_on_the_earlier_stages():
    curriculum = Curriculum(
        TerraShiftConfig.preset("large"), CurriculumSettings(stages=3, mix=0.25)
    )
    assert curriculum.allocation(100) == [(0, 100)]  # nothing earlier yet
    assert curriculum.allocation(100, stage=1) == [(0, 25), (1, 75)]
    assert curriculum.allocation(100, stage=2) == [(0, 13), (1, 12), (2, 75)]
    assert curriculum.allocation(3, stage=2) == [(0, 1), (2, 2)]  # too few for every stage
    no_mix = Curriculum(TerraShiftConfig.preset("large"), CurriculumSettings(mix=0.0))
    assert no_mix.allocation(100, stage=2) == [(2, 100)]


def tiny(**overrides) -> TerraShiftConfig:
    return TerraShiftConfig(
        **{"column_shape": "box", "max_episode_steps": 8, "heightmap_resolution": 8, **overrides}
    )


def test_the_mixed_env_pads_earlier_stages_with_absent_agents_and_empty_slots():
    small = tiny(grid_size=8, num_agents=2, num_objects=1, num_goals=1, spawn_margin=1)
    large = tiny(grid_size=12, num_agents=3, num_objects=2, num_goals=2, spawn_margin=1)
    small, large = small.replace(max_episode_steps=2), large.replace(max_episode_steps=3)
    env = MixedSceneEnv([small, large], [2, 3], seed=0)
    alone = TerraShiftEnv(large, num_envs=3, seed=1)  # the same seed as the large scene above
    td, own_td = env.reset(), alone.reset()
    generator, truncated = torch.Generator().manual_seed(0), []
    for _ in range(7):  # past the step limits: the scenes reset apart
        action = torch.rand(5, 3, 6, generator=generator) * 2 - 1
        out, td = env.step_and_maybe_reset(td.set(("agents", "action"), action))
        own, own_td = alone.step_and_maybe_reset(own_td.set(("agents", "action"), action[2:]))
        # the large scene's environments step and reset exactly as they do alone
        torch.testing.assert_close(out[2:].exclude("agents"), own.exclude("agents"))
        torch.testing.assert_close(out["next", "agents"][2:], own["next", "agents"])
        torch.testing.assert_close(td[2:].exclude("agents"), own_td.exclude("agents"))
        nxt = out["next"]
        truncated.append(nxt["truncated"][[0, 2], 0].tolist())
        assert nxt["agents", "mask"].tolist() == [[True, True, False]] * 2 + [[True] * 3] * 3
        assert (nxt["agents", "observation"][:2, 2] == 0).all()
        assert (nxt["objects"][:2, 1] == 0).all() and not nxt["objects_mask"][:2, 1].any()
        # an absent agent holds the team's reward and done flags
        for key in ("reward", "done", "terminated", "truncated"):
            torch.testing.assert_close(nxt["agents", key][:, 2], nxt["agents", key][:, 0])
    # (small, large) truncate at their step limits, 2 and 3 decisions
    assert truncated == [[0, 0], [1, 0], [0, 1], [1, 0], [0, 0], [1, 1], [0, 0]]


def test_a_mixed_env_restored_from_its_state_steps_as_the_saved_one_did():
    scenes = [tiny(num_agents=2, num_objects=1, num_goals=1), tiny(grid_size=20, num_agents=3)]
    env = MixedSceneEnv(scenes, [2, 2], seed=0)
    action = torch.zeros(4, 3, 6).uniform_(-1, 1, generator=torch.Generator().manual_seed(0))
    td = env.reset().set(("agents", "action"), action)
    for _ in range(3):
        env.step(td)
    saved = env.simulator_state()
    expected = env.step(td)["next"]
    restored = MixedSceneEnv(scenes, [2, 2], seed=123)
    restored.load_simulator_state(saved)
    torch.testing.assert_close(restored.step(td)["next"], expected)


def test_the_curriculum_env_pads_to_the_current_stages_agents_and_spheres(
    rollouts_around_an_advance,
):
    target = tiny(grid_size=12, num_agents=4, num_objects=2, num_goals=2, spawn_margin=1)
    env, before, after = rollouts_around_an_advance(target, TerraShiftModelConfig.small())
    assert [scene.grid_size for scene in env.base_env.scenes] == [8, 12]
    assert before["agents", "mask"][:, 0].tolist() == [[True, True]] * 4
    assert before["objects_mask"].shape == (4, 2, 1)
    assert after["agents", "mask"][:, 0].sum(-1).tolist() == [2, 2, 4, 4]
    assert after["objects_mask"].shape == (4, 2, 2)
    # the recurrent state follows the agents
    assert after["next", "agents", "recurrent_state"].shape[:3] == (4, 2, 4)


def test_an_advance_hands_the_trainer_the_next_stages_environments(monkeypatch):
    monkeypatch.setattr(
        curriculum_module, "evaluate_periodically", lambda *a, **k: {"eval_goal_fraction": 0.9}
    )
    curriculum, networks, hook = curriculum_run()
    config = TrainConfig(num_envs=4, steps_per_iteration=2, minibatches=1)
    trainer = make_trainer(hook.env, networks, config, scene_state=hook)
    assert trainer.collect()["agents", "mask"].shape == (4, 2, 2)
    trainer.iteration = 1
    assert hook.after_iteration(trainer)["curriculum_stage"] == 2.0
    assert trainer.env is hook.env and [s.num_agents for s in hook.env.base_env.scenes] == [2, 4]
    trainer.train_iteration()  # a reset of the new environments (staggered), then an update
    data = trainer.collect()
    assert data["agents", "mask"][:, 0].sum(-1).tolist() == [2, 2, 4, 4]
    # a checkpoint of the second stage resumes into that stage's environments
    state = trainer.state_dict()
    _, _, early = curriculum_run()
    with pytest.raises(ValueError, match="at stage 2, these environments were built at stage 1"):
        make_trainer(early.env, networks, config, scene_state=early).load_state_dict(state)
    resumed_curriculum, resumed_networks, resumed_hook = curriculum_run(state["curriculum"])
    resumed = make_trainer(resumed_hook.env, resumed_networks, config, scene_state=resumed_hook)
    resumed.load_state_dict(state)
    assert resumed_curriculum.stage == 1
    torch.manual_seed(0)
    expected = trainer.collect()
    torch.manual_seed(0)
    torch.testing.assert_close(resumed.collect(), expected)


@pytest.mark.parametrize("restart", [False, True])
def test_an_advance_restarts_the_schedules_only_if_asked(monkeypatch, restart):
    monkeypatch.setattr(
        curriculum_module, "evaluate_periodically", lambda *a, **k: {"eval_goal_fraction": 0.9}
    )
    _, networks, hook = curriculum_run(restart_schedules=restart)
    config = TrainConfig(num_envs=4, steps_per_iteration=2, minibatches=1)
    trainer = make_trainer(hook.env, networks, config, scene_state=hook)
    trainer.iteration = 3
    hook.after_iteration(trainer)
    assert trainer.schedule_start == (3 if restart else 0)


def test_a_compiled_update_compiles_for_every_stage_past_dynamos_limit(monkeypatch):
    # ten stages of 2 to 11 agents: ten shapes for each compiled network, past Dynamo's default
    # of 8 compilations per function, after which it would run that function eagerly
    monkeypatch.setattr(
        curriculum_module, "evaluate_periodically", lambda *a, **k: {"eval_goal_fraction": 0.9}
    )
    compile_module = torch.nn.Module.compile

    def compile_eagerly(module, **options):  # Dynamo's graphs without Inductor's code
        compile_module(module, dynamic=False, backend="eager")

    monkeypatch.setattr(torch.nn.Module, "compile", compile_eagerly)
    target = tiny(grid_size=12, num_agents=11, num_objects=1, num_goals=1, spawn_margin=1)
    settings = CurriculumSettings(
        stages=10, start_grid_size=8, start_num_agents=2, start_num_objects=1, eval_every=1
    )
    curriculum = Curriculum(target, settings)
    torch.manual_seed(0)
    networks = make_terrashift_networks(TerraShiftModelConfig.small())
    hook = CurriculumHook(
        curriculum, networks, lambda scene: scene, num_envs=4, device="cpu", seed=0, eval_seed=1
    )
    config = TrainConfig(num_envs=4, steps_per_iteration=2, minibatches=1, compile=True)
    graphs = []
    torch._dynamo.reset()  # no entries from other tests' compilations of the same functions
    try:
        with torch._dynamo.config.patch(recompile_limit=8):
            trainer = make_trainer(hook.env, networks, config, scene_state=hook)
            for iteration in range(1, 11):
                trainer.train_iteration()
                graphs.append(torch._dynamo.utils.counters["stats"]["unique_graphs"])
                trainer.iteration = iteration
                hook.after_iteration(trainer)
    finally:
        torch._dynamo.reset()
    assert curriculum.stage == 9
    added = [after - before for before, after in itertools.pairwise(graphs)]
    assert added == [added[0]] * 9 and added[0] > 0  # as many new graphs at the tenth stage


def curriculum_run(state=None, **settings):
    """A two-stage curriculum (8 x 8, 2 agents, 1 sphere to 12 x 12, 4 agents, 2 spheres, half
    the environments kept on the first; other ``settings`` as given), the small networks and
    its hook over 4 environments that advances at every evaluation; at ``state``'s stage if
    given."""
    target = tiny(grid_size=12, num_agents=4, num_objects=2, num_goals=2, spawn_margin=1)
    settings = CurriculumSettings(
        stages=2,
        start_grid_size=8,
        start_num_agents=2,
        start_num_objects=1,
        mix=0.5,
        eval_every=1,
        **settings,
    )
    curriculum = Curriculum(target, settings)
    if state is not None:
        curriculum.load_state_dict(state)
    torch.manual_seed(0)
    networks = make_terrashift_networks(TerraShiftModelConfig.small())
    hook = CurriculumHook(
        curriculum, networks, lambda scene: scene, num_envs=4, device="cpu", seed=0, eval_seed=1
    )
    return curriculum, networks, hook


# --- resume --------------------------------------------------------------------------------


def test_a_resumed_curriculum_continues_at_the_same_stage():
    settings = CurriculumSettings(stages=4)
    curriculum = Curriculum(TerraShiftConfig.preset("large"), settings)
    curriculum.advance(env_steps=1_000)
    curriculum.advance(env_steps=5_000)
    resumed = Curriculum(TerraShiftConfig.preset("large"), settings)
    resumed.load_state_dict(curriculum.state_dict())
    assert (resumed.stage, resumed.advances) == (2, [1_000, 5_000])
    assert resumed.scene == curriculum.scene
    assert resumed.allocation(64) == curriculum.allocation(64)
    other = Curriculum(TerraShiftConfig.preset("large"), CurriculumSettings(stages=3))
    with pytest.raises(ValueError, match="resume with the curriculum and env settings"):
        other.load_state_dict(curriculum.state_dict())


# --- refusals ------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("target", "settings", "message"),
    [
        ({"grid_size": 10}, {}, r"env.grid_size \(10\) is smaller than curriculum.start_grid"),
        ({"num_agents": 4}, {}, r"env.num_agents \(4\) is smaller than curriculum.start_num_ag"),
        ({"num_objects": 2, "num_goals": 2}, {}, "env.num_objects .* curriculum.start_num_obj"),
        ({}, {}, "nothing to grow; use curriculum=none"),
        (
            {"grid_size": 30},
            {"start_grid_size": 4},
            r"stage 1 of 3 \(4x4 columns, 8 agents, 4 spheres\) is no scene the simulator holds",
        ),
        ({"grid_size": 30}, {"stages": 1}, "curriculum.stages must be an integer >= 2, got 1"),
        (
            {"grid_size": 30},
            {"threshold": -0.1},
            r"curriculum.threshold must be a finite number in \[0, 1\], got -0.1",
        ),
        (
            {"grid_size": 30},
            {"mix": 1.0},
            r"curriculum.mix must be a finite number in \[0, 1\), got 1.0",
        ),
        ({"grid_size": 30}, {"kind": "manual"}, "curriculum.kind must be one of"),
        ({"grid_size": 30}, {"eval_every": 0}, "curriculum.eval_every must be an integer >= 1"),
        (
            {"grid_size": 30},
            {"retention_every": 0},
            r"curriculum.retention_every must be .* or null",
        ),
    ],
)
def test_an_inconsistent_curriculum_is_refused_naming_the_setting(target, settings, message):
    with pytest.raises(ValueError, match=message):
        Curriculum(TerraShiftConfig(**target), CurriculumSettings(**settings))


@pytest.mark.parametrize(
    ("training", "message"),
    [
        ({"algo": "ippo"}, "only train.algo=mapoca's loss leaves out; got train.algo=ippo"),
        ({"teacher": True}, "set loss.teacher_coeff=0"),
        ({"num_envs": 1}, "train.num_envs=1 with curriculum.mix=0.9 leaves no environment"),
    ],
)
def test_training_settings_a_curriculum_cannot_train_with_are_refused(training, message):
    curriculum = Curriculum(TerraShiftConfig.preset("large"), CurriculumSettings(mix=0.9))
    curriculum.check_training(algo="mapoca", teacher=False, num_envs=64)
    with pytest.raises(ValueError, match=message):
        curriculum.check_training(
            **{"algo": "mapoca", "teacher": False, "num_envs": 64, **training}
        )


def test_a_mixed_env_of_scenes_or_counts_that_do_not_fit_is_refused():
    with pytest.raises(ValueError, match="a 16-ray heightmap does not fit this env's"):
        MixedSceneEnv([tiny(), tiny(heightmap_resolution=16)], [1, 1])
    with pytest.raises(ValueError, match="10 agents, 4 spheres .* does not fit this env's 9"):
        MixedSceneEnv([tiny(num_agents=10)], [2], num_agents=9, num_objects=5)
    with pytest.raises(ValueError, match=r"one count of environments per scene, got 2 scene"):
        MixedSceneEnv([tiny(), tiny()], [3])
    with pytest.raises(ValueError, match=r"num_envs must hold integers >= 1, got \[2, 0\]"):
        MixedSceneEnv([tiny(), tiny()], [2, 0])
    with pytest.raises(ValueError, match="needs at least one scene"):
        MixedSceneEnv([], [])


def test_ma_pocas_loss_on_a_padded_scene_equals_its_loss_on_the_scene_alone():
    """The mix pads earlier stages with absent agents and empty slots: MA-POCA's estimate and
    loss on a stage's environments come out the same padded as alone."""
    small = tiny(grid_size=8, num_agents=2, num_objects=1, num_goals=1, spawn_margin=1)
    large = tiny(grid_size=12, num_agents=3, num_objects=2, num_goals=2, spawn_margin=1)
    torch.manual_seed(0)
    networks = make_terrashift_networks(TerraShiftModelConfig.small()).eval()
    algorithm = MAPOCAConfig().make(networks, max_batch=2)
    losses = []
    for scenes, counts in (([small], [2]), ([small, large], [2, 1])):
        env = TransformedEnv(
            MixedSceneEnv(scenes, counts, seed=0),
            Compose(InitTracker(), networks.make_tensordict_primer(scenes[-1].num_agents)),
        )
        with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
            data = env.rollout(6, networks.actor)[:2]  # the small scene's environments
        algorithm.value_normalizer.load_state_dict(ValueNormalizer().state_dict())
        with torch.no_grad(), set_recurrent_mode(True):
            algorithm.estimate(data)
            losses.append(algorithm.loss(data))
    alone, padded = losses
    for term in ("loss_objective", "loss_critic", "loss_baseline", "loss_entropy"):
        torch.testing.assert_close(padded[term], alone[term], rtol=1e-4, atol=1e-6)


def test_a_curriculum_scene_the_networks_cannot_read_is_refused_naming_the_settings():
    """The curriculum's environments are checked against the networks as a single scene's are:
    networks reading a camera on a target without one are refused before any env is built."""
    target = TerraShiftConfig(grid_size=12, num_agents=3, num_objects=2, num_goals=2)
    settings = CurriculumSettings(
        stages=2, start_grid_size=8, start_num_agents=2, start_num_objects=1, mix=0.5
    )
    networks = make_terrashift_networks(
        dataclasses.replace(TerraShiftModelConfig.small(), camera_channels=1)
    )
    with pytest.raises(ValueError, match="camera_channels=1 but env.camera_resolution=0"):
        make_curriculum_env(
            Curriculum(target, settings), networks, num_envs=4, device="cpu", seed=0
        )
