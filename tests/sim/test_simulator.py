"""Simulator state: a state_dict restores every environment exactly, also one saved before a
data array was renamed or added. A simulator loads, when built, the Warp modules its steps and
resets launch and no others."""

import dataclasses

import pytest
import torch
import warp as wp

from terrashift_rl.sim import Simulator, TerraShiftConfig, camera, physics
from terrashift_rl.sim.actuators import ACTUATORS
from terrashift_rl.sim.actuators.patches import sliding_kernel

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


@pytest.mark.parametrize("camera_resolution", [0, 4], ids=["no_camera", "camera"])
@pytest.mark.parametrize("fuse_substeps", [True, False], ids=["fused", "per_substep"])
def test_a_wavelet_simulator_loads_what_it_launches_when_built_and_nothing_else(
    monkeypatch, fuse_substeps, camera_resolution
):
    requested: list[str] = []
    load = wp.Module.load

    def recording_load(module, *args, **kwargs):
        requested.append(module.name)
        return load(module, *args, **kwargs)

    monkeypatch.setattr(wp.Module, "load", recording_load)
    config = dataclasses.replace(CONFIG, camera_resolution=camera_resolution)
    sim = Simulator(config, num_envs=2, seed=0, fuse_substeps=fuse_substeps)
    built = set(requested)
    sim.reset()
    sim.step(torch.zeros(sim.action_shape))
    # a CUDA graph captured after construction launches only modules loaded before it
    assert set(requested) <= built
    substep, tick_substeps = physics.sphere_kernels(False, CONFIG.count_surface_work)
    used, unused = (tick_substeps, substep) if fuse_substeps else (substep, tick_substeps)
    assert used.module.name in built
    assert (camera.__name__ in built) == bool(camera_resolution)
    never = {unused.module.name, physics.__name__}
    for family in ACTUATORS.values():
        if family.moves_surface:
            never |= {type(family).__module__, sliding_kernel(family.patch_velocity).module.name}
    assert not never & built
