"""evaluate / evaluate_baselines: one episode per environment, metrics a hand count agrees with;
a trainer's evaluation policy, replayed as CUDA graphs, against the eager actor."""

import math

import pytest
import torch
from torchrl.envs import InitTracker, StepCounter, TransformedEnv

from terrashift_rl.envs import GROUP, TerraShiftEnv
from terrashift_rl.envs.baselines import RandomPolicy, ScriptedHeuristicPolicy, ZeroPolicy
from terrashift_rl.modules import TerraShiftModelConfig, make_terrashift_networks
from terrashift_rl.sim import REWARD_TERMS, TerraShiftConfig
from terrashift_rl.training import TrainConfig, make_training_env, terrashift
from terrashift_rl.training.evaluation import (
    HEADLINE,
    evaluate,
    evaluate_baselines,
    evaluate_periodically,
    evaluation_scene,
)
from terrashift_rl.training.graphs import CudaGraphed

STEPS = 96
CFG = TerraShiftConfig(max_episode_steps=STEPS, respawn=False)


def hand_count(env: TerraShiftEnv, policy, steps: int) -> dict[str, torch.Tensor]:
    """Per-environment results of the first episode, from a plain auto-resetting rollout."""
    data = env.rollout(steps, policy, break_when_any_done=False)
    done = data["next", "done"].squeeze(-1)  # [N, T]
    assert done.any(-1).all(), "every environment ends within max_episode_steps"
    end = done.long().argmax(-1)  # first done step
    rows = torch.arange(env.num_envs)
    reward = data["next", GROUP, "reward"][..., 0, 0]
    in_episode = torch.arange(steps) <= end.unsqueeze(-1)
    return {
        "length": end + 1,
        "goals": data["next", "episode_goals"].squeeze(-1)[rows, end],
        "lost": data["next", "episode_out_of_bounds"].squeeze(-1)[rows, end],
        "terminated": data["next", "terminated"].squeeze(-1)[rows, end],
        "reward": (reward * in_episode).sum(-1) / (end + 1),
    }


@pytest.mark.parametrize("name", ["heuristic", "random"])
def test_metrics_match_a_hand_count(name):
    n, seed = 6, 3

    def make():
        return ScriptedHeuristicPolicy(CFG) if name == "heuristic" else RandomPolicy(seed=seed)

    metrics = evaluate(TerraShiftEnv(CFG, num_envs=n, seed=seed), make(), progress=False)
    ref = hand_count(TerraShiftEnv(CFG, num_envs=n, seed=seed), make(), STEPS)
    goals, lost = ref["goals"].sum().item(), ref["lost"].sum().item()
    assert metrics["episodes"] == n
    assert metrics["goals_per_episode"] == pytest.approx(goals / n)
    assert metrics["out_of_bounds_per_episode"] == pytest.approx(lost / n)
    assert metrics["goal_fraction"] == pytest.approx(goals / (n * CFG.num_objects))
    expected_success = goals / (goals + lost) if goals + lost else 0.0
    assert metrics["success_rate"] == pytest.approx(expected_success)
    assert metrics["mean_episode_length"] == pytest.approx(ref["length"].float().mean().item())
    assert metrics["terminated_fraction"] == pytest.approx(ref["terminated"].float().mean().item())
    assert metrics["mean_reward_per_decision"] == pytest.approx(
        ref["reward"].mean().item(), rel=1e-5, abs=1e-7
    )
    assert 0.0 <= metrics["success_rate"] <= 1.0
    if name == "heuristic":
        # the seeded heuristic run ends some episodes early (every sphere resolved), so the
        # comparison above covers steps after an environment's first episode being ignored
        assert (ref["length"] < STEPS).any() and (ref["length"] == STEPS).any()


def test_one_episode_per_environment_through_a_transformed_env():
    n, seed = 4, 5
    base = TerraShiftEnv(CFG, num_envs=n, seed=seed)
    env = TransformedEnv(base, InitTracker())
    env.append_transform(StepCounter())
    wrapped = evaluate(env, ScriptedHeuristicPolicy(CFG), episodes=n, progress=True)
    plain = evaluate(
        TerraShiftEnv(CFG, num_envs=n, seed=seed), ScriptedHeuristicPolicy(CFG), progress=False
    )
    assert wrapped == plain
    assert wrapped["episodes"] == n
    assert 1 <= wrapped["mean_episode_length"] <= STEPS


def test_nothing_resolved_gives_a_zero_success_rate_not_nan():
    env = TerraShiftEnv(CFG.replace(max_episode_steps=1), num_envs=3, seed=0)
    metrics = evaluate(env, ZeroPolicy(), progress=False)
    assert metrics["goals_per_episode"] == 0 and metrics["out_of_bounds_per_episode"] == 0
    assert metrics["success_rate"] == 0.0
    assert metrics["mean_episode_length"] == 1 and metrics["terminated_fraction"] == 0
    assert all(math.isfinite(value) for value in metrics.values())


def test_rejects_a_wrong_episode_count():
    with pytest.raises(ValueError, match="episodes"):
        evaluate(TerraShiftEnv(CFG, num_envs=2, seed=0), ZeroPolicy(), episodes=3)


def test_training_mode_runs_every_episode_to_the_step_limit():
    n, seed, steps = 4, 3, 48
    config = CFG.replace(respawn=True, max_episode_steps=steps)
    policy = ScriptedHeuristicPolicy(config)
    metrics = evaluate(TerraShiftEnv(config, num_envs=n, seed=seed), policy, progress=False)
    ref = hand_count(TerraShiftEnv(config, num_envs=n, seed=seed), policy, steps)
    assert (ref["length"] == steps).all() and not ref["terminated"].any()
    assert metrics["mean_episode_length"] == steps and metrics["terminated_fraction"] == 0
    assert metrics["goals_per_episode"] == pytest.approx(ref["goals"].sum().item() / n)
    assert metrics["out_of_bounds_per_episode"] == pytest.approx(ref["lost"].sum().item() / n)
    assert metrics["mean_reward_per_decision"] == pytest.approx(
        ref["reward"].mean().item(), rel=1e-5, abs=1e-7
    )
    baselines = evaluate_baselines(
        config.replace(respawn=False), num_envs=n, seed=seed, respawn=True
    )
    assert baselines["heuristic"] == metrics
    assert all(scores["mean_episode_length"] == steps for scores in baselines.values())


SHAPING = [name for name, role in REWARD_TERMS.items() if role == "shaping"]


def test_evaluation_scene_switches_off_every_shaping_term_and_keeps_the_task_terms():
    values = {name: 0.25 * (i + 1) for i, name in enumerate(REWARD_TERMS)}
    scene = evaluation_scene(TerraShiftConfig(**values), respawn=True)
    assert {name: getattr(scene, name) for name in REWARD_TERMS} == {
        name: 0.0 if name in SHAPING else value for name, value in values.items()
    }
    assert scene.respawn and not evaluation_scene(scene).respawn


@pytest.mark.parametrize("term", SHAPING)
def test_evaluation_scores_the_reward_without_the_shaping_term(term):
    # the heuristic drives its wavelets to the spheres and the spheres to their goals, which
    # every shaping term pays for
    n, seed, steps = 4, 3, 48
    config = CFG.replace(max_episode_steps=steps)
    shaped = config.replace(**{term: 1.0})
    policy = ScriptedHeuristicPolicy(config)
    trained_on = evaluate(TerraShiftEnv(shaped, num_envs=n, seed=seed), policy, progress=False)
    plain = evaluate(TerraShiftEnv(config, num_envs=n, seed=seed), policy, progress=False)
    assert trained_on["mean_reward_per_decision"] != pytest.approx(
        plain["mean_reward_per_decision"], rel=1e-3
    )
    baselines = evaluate_baselines(shaped, num_envs=n, seed=seed)
    assert baselines["heuristic"] == plain


def test_baselines_of_a_pixels_scene_read_the_objects_and_face_the_same_scenes():
    n, seed, config = 3, 2, CFG.replace(max_episode_steps=24)
    pixels = config.replace(camera_resolution=16, observe_objects=False, privileged_objects=True)
    assert evaluate_baselines(pixels, num_envs=n, seed=seed) == evaluate_baselines(
        config, num_envs=n, seed=seed
    )


def test_heuristic_beats_random_and_zero():
    # measured (16 envs, 128 decisions, seed 0): goals per episode heuristic 2.56, random 0.0,
    # zero 0.0; mean reward per decision 0.28 vs -0.034 and -0.034
    config = TerraShiftConfig(max_episode_steps=128)
    scores = evaluate_baselines(config, num_envs=16, device="cpu", seed=0)
    assert sorted(scores) == ["heuristic", "random", "zero"]
    heuristic = scores["heuristic"]
    for name in ("random", "zero"):
        other = scores[name]
        assert other["episodes"] == 16
        assert heuristic["goals_per_episode"] > other["goals_per_episode"] + 1.0
        assert heuristic["success_rate"] > other["success_rate"]
        assert heuristic["mean_reward_per_decision"] > other["mean_reward_per_decision"]


def test_periodic_evaluation_scores_the_mean_action_on_the_same_scenes_each_time():
    scene = TerraShiftConfig(max_episode_steps=12, respawn=False)
    networks = make_terrashift_networks(TerraShiftModelConfig.small())
    env = make_training_env(scene, networks, num_envs=4, device=torch.device("cpu"), seed=5)
    first = evaluate_periodically(env, networks.actor, seed=5)
    assert list(first) == [f"eval_{name}" for name in HEADLINE]
    env.rollout(7, break_when_any_done=False)  # moves the environments' generator on
    assert evaluate_periodically(env, networks.actor, seed=5) == first  # same scenes, mean action
    assert evaluate_periodically(env, networks.actor, seed=6) != first  # other scenes


def test_periodic_evaluation_scores_the_samples_too_without_touching_training_randomness():
    scene = TerraShiftConfig(max_episode_steps=12, respawn=False)
    networks = make_terrashift_networks(TerraShiftModelConfig.small())
    env = make_training_env(scene, networks, num_envs=4, device=torch.device("cpu"), seed=5)
    state = torch.get_rng_state()
    first = evaluate_periodically(env, networks.actor, seed=5, sampled=True)
    assert torch.equal(torch.get_rng_state(), state)  # training's stream goes on as it was
    expected = [f"eval_{name}" for name in HEADLINE]
    assert list(first) == expected + [f"eval_sampled_{name}" for name in HEADLINE]
    assert {k: first[k] for k in expected} == evaluate_periodically(env, networks.actor, seed=5)
    # the samples are seeded too: the same scores again, and not the mean action's
    assert evaluate_periodically(env, networks.actor, seed=5, sampled=True) == first
    sampled = [first[f"eval_sampled_{name}"] for name in HEADLINE]
    assert sampled != [first[f"eval_{name}"] for name in HEADLINE]


PERIODIC = TerraShiftConfig(max_episode_steps=12, respawn=False)
CUDA = torch.device("cuda")


def trainer_of(networks, device: torch.device, *, cuda_graphs: bool = True):
    """A trainer of ``networks`` on four environments of :data:`PERIODIC`."""
    env = make_training_env(PERIODIC, networks, num_envs=4, device=device, seed=0)
    config = TrainConfig(
        num_envs=4, steps_per_iteration=8, minibatches=1, tf32=False, cuda_graphs=cuda_graphs
    )
    return terrashift.make_trainer(env, networks, config)


def scored(trainer, env) -> dict[str, float]:
    """The periodic evaluation's mean and sampled scores of ``trainer``'s evaluation policy."""
    policies = trainer.evaluation_policy
    return evaluate_periodically(env, trainer.policy, seed=5, sampled=True, policies=policies)


def test_a_trainers_evaluation_policy_scores_as_the_actor_does_on_the_cpu():
    networks = make_terrashift_networks(TerraShiftModelConfig.small())
    trainer = trainer_of(networks, torch.device("cpu"))
    env = make_training_env(PERIODIC, networks, num_envs=4, device=torch.device("cpu"), seed=5)
    assert scored(trainer, env) == evaluate_periodically(env, networks.actor, seed=5, sampled=True)
    steps = trainer._evaluation_steps.values()
    assert len(steps) == 2  # one per exploration type, eager off CUDA
    assert not any(isinstance(step, CudaGraphed) for step in steps)


@pytest.mark.gpu
def test_a_trainers_evaluation_replays_the_policy_as_graphs_kept_across_evaluations():
    torch.manual_seed(0)
    networks = make_terrashift_networks(TerraShiftModelConfig.small()).to(CUDA)
    envs = [make_training_env(PERIODIC, networks, num_envs=n, device=CUDA, seed=0) for n in (4, 6)]
    scores = {}
    for graphs in (False, True):
        trainer = trainer_of(networks, CUDA, cuda_graphs=graphs)
        steps = trainer._evaluation_steps
        first = scored(trainer, envs[0])
        kept = dict(steps)  # one step per exploration type
        # again on the same environments, then on six: other shapes, other steps
        scores[graphs] = [first, scored(trainer, envs[0]), scored(trainer, envs[1])]
        assert len(kept) == 2 and all(steps[key] is step for key, step in kept.items())
        assert len(steps) == 4
        assert all(isinstance(step, CudaGraphed) == graphs for step in steps.values())
        if graphs:  # captured at the first evaluation of each shape, replayed at the second
            assert all(step.captured for step in steps.values())
    replayed, eager = scores[True], scores[False]
    assert replayed[0] == replayed[1]  # the same scenes, samples and replays
    # A graph replays the kernels of an eager call, but cuBLAS may choose other algorithms for
    # a capture, so the mean actions can differ in their last bits: the outcomes of 12
    # decisions are the same, the rewards the same up to rounding.
    for graphed, plain in zip(replayed, eager, strict=True):
        for name in HEADLINE:
            key = f"eval_{name}"
            if name == "mean_reward_per_decision":
                assert graphed[key] == pytest.approx(plain[key], rel=1e-4, abs=1e-6)
            else:
                assert graphed[key] == plain[key], key
