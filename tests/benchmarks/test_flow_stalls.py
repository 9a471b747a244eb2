"""flow_stalls.py: the sliding families' heuristic with and without steering clear."""

import math
import sys
from pathlib import Path

import pytest
import torch

from terrashift_rl.sim import ScriptedScene, TerraShiftConfig
from terrashift_rl.training.evaluation import evaluation_scene

sys.path.insert(0, str(Path(__file__).parents[2] / "benchmarks"))

import flow_stalls  # noqa: E402


def test_stored_spin_of_a_sphere_rolling_in_place_is_minus_two_fifths_of_the_flow():
    """Still, spinning so that its contact point rides a surface at u along x: C = -2u/5."""
    cfg = TerraShiftConfig(actuator="surface_flow", column_shape="box", num_objects=1, num_goals=1)
    scene = ScriptedScene(cfg)
    u, r = 0.8, cfg.sphere_radius
    scene.place_spheres(
        torch.tensor([[0.0, 0.0, 0.2]]), angular_velocities=torch.tensor([[0.0, -u / r, 0.0]])
    )
    spin = flow_stalls.stored_spin(scene.sim)[0, 0]
    torch.testing.assert_close(spin, torch.tensor([-0.4 * u, 0.0]))


@pytest.mark.parametrize("clearance", [None, 2.0])
@pytest.mark.parametrize("actuator", ["surface_flow", "rotors"])
def test_every_metric_is_a_count_or_share_in_range(actuator, clearance):
    config = evaluation_scene(
        TerraShiftConfig(
            actuator=actuator,
            column_shape="box",
            action_mode="shape",
            count_surface_work=True,
            max_episode_steps=40,
        )
    )
    scores = flow_stalls.play(config, clearance, num_envs=4, seed=0)
    assert 0.0 <= scores["goal_fraction"] <= 1.0
    assert 1.0 <= scores["mean_episode_length"] <= 40.0
    for share in ("truncated_fraction", "rolling_in_place"):
        assert 0.0 <= scores[share] <= 1.0
    assert 0.0 <= scores["spun_up_after_contact"] <= scores["spun_up"] <= config.num_objects
    assert math.isfinite(scores["surface_work_per_goal"]) and scores["surface_work_per_goal"] >= 0
