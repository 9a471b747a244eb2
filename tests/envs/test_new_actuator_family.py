"""A family added as docs/actuators.md says, here defined in this file alone: registering
itself makes the config, the simulator, the environment and every baseline take it."""

import numpy as np
import pytest
import torch
import warp as wp
from torchrl.envs.utils import check_env_specs

from terrashift_rl.envs import GROUP, TerraShiftEnv
from terrashift_rl.envs.baselines import RandomPolicy, ScriptedHeuristicPolicy, ZeroPolicy
from terrashift_rl.sim import ACTUATORS, TerraShiftConfig
from terrashift_rl.sim.actuators import register
from terrashift_rl.sim.actuators.patches import SlidingPatchActuator
from terrashift_rl.sim.types import Model


@wp.func
def funnel_velocity(model: Model, amplitude: float, frame: wp.vec4, envelope: wp.vec3) -> wp.vec2:
    """One patch's surface flowing towards its centre: its rate [1/s] times its envelope times
    the offset from the column back to the centre [m]."""
    return (-amplitude * envelope[0] * model.cell_size) * wp.vec2(envelope[1], envelope[2])


@pytest.fixture
def funnels():
    """Registers a sliding family of its own for one test, with the config's rotor limits."""

    @register
    class Funnels(SlidingPatchActuator):
        name = "funnels"
        patch_velocity = funnel_velocity

        def amplitude_limits(self, config: TerraShiftConfig) -> tuple[float, float, float]:
            return -config.max_rotor_speed, config.max_rotor_speed, config.rotor_speed_gain

    yield Funnels
    del ACTUATORS["funnels"]


def test_a_family_defined_outside_the_package_runs_through_the_environment(funnels):
    env = TerraShiftEnv(
        num_envs=2, seed=0, actuator="funnels", column_shape="box", max_episode_steps=8
    )
    assert isinstance(env.sim.actuator, funnels)
    check_env_specs(env, seed=0)
    for policy in (RandomPolicy(seed=0), ZeroPolicy(), ScriptedHeuristicPolicy(env.config)):
        td = env.rollout(10, policy, break_when_any_done=False)
        assert torch.isfinite(td["next", GROUP, "reward"]).all()

    # the surface is the family's: with one patch of positive rate, it flows to the centre
    sim = env.sim
    sim.view("agent_amplitude").fill_(env.config.max_rotor_speed)
    sim.view("agent_amplitude")[:, 1:] = 0.0
    sim.view("agent_velocity").zero_()
    sim.view("agent_angular_velocity").zero_()
    sim.step(torch.zeros(sim.action_shape))  # zero rates and actions: the patches stay put
    flow = sim.view("surface_velocity").double().numpy()  # [envs, G(y), G(x), 2]
    g = env.config.grid_size
    iy, ix = np.meshgrid(np.arange(g), np.arange(g), indexing="ij")
    for e, (x, y) in enumerate(sim.view("agent_position")[:, 0].double().numpy()):
        # offsets from the patch's centre, the short way round the torus
        offset = np.stack([ix - x, iy - y], axis=-1)
        offset -= g * np.floor(offset / g + 0.5)
        inward = -(flow[e] * offset).sum(-1)
        assert inward.max() > 1e-3
        assert inward.min() >= -1e-6
    assert (sim.view("column_height") == 0).all()


def test_a_family_is_refused_once_it_is_no_longer_registered():
    with pytest.raises(ValueError, match="actuator must be one of .* got 'funnels'"):
        TerraShiftConfig(actuator="funnels")
