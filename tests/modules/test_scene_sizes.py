"""One set of weights acts on TerraShift scenes of every size a curriculum passes through."""

from __future__ import annotations

import pytest
import torch
from torchrl.envs import Compose, InitTracker, TransformedEnv

from terrashift_rl.envs import TerraShiftEnv
from terrashift_rl.modules import keys
from terrashift_rl.sim import TerraShiftConfig

SCENES = {
    "pretrain-15x15-8-agents-4-spheres": TerraShiftConfig.preset("pretrain"),
    "30x30-16-agents-6-spheres": TerraShiftConfig.preset("finetune", num_objects=6, num_goals=6),
    "large-45x45-24-agents-8-spheres": TerraShiftConfig.preset("large"),
}


@pytest.mark.parametrize("scene", SCENES.values(), ids=SCENES.keys())
def test_one_set_of_weights_acts_and_values_every_scene(networks, scene):
    """The same parameters (the small preset) roll out and value a real scene of each size:
    actions, log-probabilities, values and baselines come out with the scene's shapes."""
    weights = {name: value.clone() for name, value in networks.state_dict().items()}
    env = TransformedEnv(
        TerraShiftEnv(scene, num_envs=2, seed=0),
        Compose(InitTracker(), networks.make_tensordict_primer(scene.num_agents)),
    )
    with torch.no_grad():
        rollout = env.rollout(3, networks.actor)
        valued = networks.baseline_head(networks.value_network(rollout.clone()))
    k, m = scene.num_agents, scene.num_objects
    assert rollout[keys.ACTION].shape == (2, 3, k, 6)
    assert rollout[keys.OBJECTS].shape == (2, 3, m, 9)
    assert rollout[keys.ACTION_LOG_PROB].isfinite().all()
    assert valued[keys.STATE_VALUE].shape == (2, 3, 1)
    assert valued[keys.BASELINE].shape == (2, 3, k, 1)
    assert valued[keys.STATE_VALUE].isfinite().all() and valued[keys.BASELINE].isfinite().all()
    for name, value in networks.state_dict().items():  # no scene resized a parameter
        assert torch.equal(value, weights[name]), name
