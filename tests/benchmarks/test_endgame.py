"""endgame.py: its pace and resolutions agree with evaluate(); its amplitude shares follow the
wavelets' amplitudes."""

import sys
from pathlib import Path

import pytest
import torch

sys.path.insert(0, str(Path(__file__).parents[2] / "benchmarks"))

import endgame  # noqa: E402

from terrashift_rl.envs import TerraShiftEnv
from terrashift_rl.envs.baselines import ScriptedHeuristicPolicy
from terrashift_rl.sim import Simulator, TerraShiftConfig
from terrashift_rl.training.evaluation import evaluate

SCENE = TerraShiftConfig(respawn=False, max_episode_steps=120)


def test_goals_and_losses_match_evaluate_on_the_same_scenes():
    policy = ScriptedHeuristicPolicy(SCENE)
    env = TerraShiftEnv(SCENE, num_envs=8, seed=1)
    row = endgame.endgame(env, env.sim, policy, SCENE)
    scores = evaluate(TerraShiftEnv(SCENE, num_envs=8, seed=1), policy, progress=False)
    reached = list(row["goal_fraction_by_decision"].values())
    assert row["goal_fraction_by_decision"]["120"] == pytest.approx(scores["goal_fraction"])
    assert row["lost_fraction"] == pytest.approx(
        scores["out_of_bounds_per_episode"] / SCENE.num_objects
    )
    assert reached == sorted(reached) and 0 < reached[0] < reached[-1]
    # every sphere spawns within the first decisions: each is at its goal, lost or unresolved
    total = reached[-1] + row["lost_fraction"] + row["unresolved_fraction"]
    assert total == pytest.approx(1.0)
    assert 0 < row["decisions_to_goal_median"] <= row["decisions_to_goal_p90"] <= 120
    assert row["share_negative_amplitude"] < 0.2  # the heuristic raises bumps


@pytest.mark.parametrize(("ratio", "negative"), [(-1.0, True), (0.0, False)])
def test_amplitudes_pressed_down_sit_at_the_floor(ratio, negative):
    scene = SCENE.replace(max_episode_steps=40, min_amplitude_ratio=ratio)
    env = TerraShiftEnv(scene, num_envs=4, seed=0)

    def press_down(td):
        action = torch.zeros(4, scene.num_agents, 6)
        action[..., 3] = -1.0
        return td.set(("agents", "action"), action)

    row = endgame.endgame(env, env.sim, press_down, scene)
    # 0.006 m lower a decision: from at most +max_amplitude (0.06 m) the floor is at most 20
    # decisions away with ratio -1 (and zero at most 10), 10 with ratio 0
    if negative:
        assert row["share_negative_amplitude"] > 0.7
        assert row["share_at_amplitude_floor"] > 0.45
    else:
        assert row["share_negative_amplitude"] == 0.0
        assert row["share_at_amplitude_floor"] > 0.7


def test_a_training_scene_is_refused():
    env = TerraShiftEnv(TerraShiftConfig(max_episode_steps=8), num_envs=2, seed=0)
    with pytest.raises(ValueError, match="evaluation mode"):
        endgame.endgame(env, env.sim, ScriptedHeuristicPolicy(env.config), env.config)


def test_each_wavelet_counts_for_its_nearest_active_sphere_the_short_way_round():
    scene = TerraShiftConfig(num_agents=5, num_objects=3, num_goals=3)
    sim = Simulator(scene, num_envs=1, seed=0)
    sim.reset()
    cells = torch.tensor([[[2.0, 2.0], [10.0, 2.0], [2.0, 10.0]]])
    sim.view("sphere_position")[..., :2].copy_((cells + 0.5) * scene.cell_size - 0.5)
    sim.view("sphere_active").copy_(torch.tensor([[1, 1, 0]], dtype=torch.int32))
    # (2, 9) lies nearest the inactive sphere 2, then sphere 0; (14, 2) is 3 cells from
    # sphere 0 round the wrapping edge and 4 from sphere 1
    agents = [[3.0, 2.0], [2.0, 3.0], [9.0, 2.0], [2.0, 9.0], [14.0, 2.0]]
    sim.view("agent_position").copy_(torch.tensor([agents]))
    assert endgame.wavelets_nearest_to(sim, scene).tolist() == [[4, 1, 0]]
