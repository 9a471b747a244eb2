"""Simulator state: a state_dict restores every environment exactly, also one saved before a
data array was renamed or added."""

import pytest
import torch

from terrashift_rl.sim import Simulator, TerraShiftConfig

CONFIG = TerraShiftConfig(grid_size=8, num_agents=4, num_objects=2, num_goals=2, spawn_margin=1)


def test_a_restored_state_steps_as_the_saved_one_did():
    sim = Simulator(CONFIG, num_envs=3, seed=0)
    sim.reset()
    action = torch.rand(sim.action_shape, generator=torch.Generator().manual_seed(0)) * 2 - 1
    sim.step(action)
    state = sim.state_dict()
    sim.step(action)
    stepped = sim.state_dict()
    sim.load_state_dict(state)
    sim.step(action)
    for name, value in sim.state_dict().items():
        torch.testing.assert_close(value, stepped[name], atol=0, rtol=0, msg=name)


def test_a_state_saved_under_an_earlier_array_name_loads():
    sim = Simulator(CONFIG, num_envs=3, seed=0)
    sim.reset(torch.tensor([True, False, True]))
    state = sim.state_dict()
    earlier = {
        ("env_mask" if name == "reset_mask" else name): value for name, value in state.items()
    }
    assert "reset_mask" not in earlier
    sim.reset()
    sim.load_state_dict(earlier)
    assert sim.view("reset_mask").tolist() == [True, False, True]


@pytest.mark.parametrize("added", ["approach_gap", "sphere_approach_gap"])
def test_a_state_saved_before_an_array_was_added_loads_with_its_start_value(added):
    sim = Simulator(CONFIG, num_envs=3, seed=0)
    sim.reset()
    state = {name: value for name, value in sim.state_dict().items() if name != added}
    sim.view(added).fill_(2.0)
    sim.load_state_dict(state)
    assert sim.view(added).eq(-1.0).all()
