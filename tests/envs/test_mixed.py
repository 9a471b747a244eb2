"""The mixed-scene env with the overhead camera: every scene's frame at one resolution, with
or without the object sequence (or with it for the critics alone), through a curriculum's
advance; scenes that observe otherwise are refused."""

from __future__ import annotations

import dataclasses

import pytest
import torch
from torchrl.envs.utils import check_env_specs

from terrashift_rl.envs.mixed import MixedSceneEnv
from terrashift_rl.modules import TerraShiftModelConfig
from terrashift_rl.sim import TerraShiftConfig

CAMERA = 16


def scene(**overrides) -> TerraShiftConfig:
    return TerraShiftConfig(
        **{
            "column_shape": "box",
            "max_episode_steps": 8,
            "heightmap_resolution": 8,
            "camera_resolution": CAMERA,
            "spawn_margin": 1,
            **overrides,
        }
    )


SMALL = {"grid_size": 8, "num_agents": 2, "num_objects": 1, "num_goals": 1}
LARGE = {"grid_size": 12, "num_agents": 3, "num_objects": 2, "num_goals": 2}


@pytest.mark.parametrize(
    ("observe_objects", "privileged_objects"), [(True, False), (False, False), (False, True)]
)
def test_every_scene_renders_its_own_frames_at_the_envs_resolution(
    observe_objects, privileged_objects
):
    observed = {"observe_objects": observe_objects, "privileged_objects": privileged_objects}
    small = scene(**SMALL, **observed)
    large = scene(**LARGE, **observed)
    env = MixedSceneEnv([small, large], [2, 1], seed=0)
    check_env_specs(env)
    td = env.rollout(3)
    assert td["camera"].shape == (3, 3, 1, CAMERA, CAMERA)
    assert ("objects" in td) == observe_objects
    assert ("privileged" in td) == privileged_objects
    if observe_objects or privileged_objects:  # each scene's spheres, the small one padded
        root = () if observe_objects else ("privileged",)
        objects, mask = (td["next", (*root, key)][:, -1] for key in ("objects", "objects_mask"))
        assert torch.equal(objects[:2, :1], env.envs[0].sim.view("object_features"))
        assert torch.equal(mask[2:], env.envs[1].sim.view("object_mask"))
        assert objects[:2, 1].eq(0).all() and not mask[:2, 1].any()
    # each scene's rows are the frames its own simulator drew, padded agents or not
    last = td["next", "camera"][:, -1]
    assert torch.equal(last[:2], env.envs[0].sim.view("camera"))
    assert torch.equal(last[2:], env.envs[1].sim.view("camera"))
    assert not torch.equal(last[0], last[2])


def test_a_scene_that_observes_otherwise_is_refused_by_name():
    with pytest.raises(ValueError, match="camera_resolution=8, observe_objects=True, privil"):
        MixedSceneEnv([scene(), scene(camera_resolution=8)], [1, 1])
    with pytest.raises(ValueError, match="observe_objects=False, privileged_objects=False does"):
        MixedSceneEnv([scene(), scene(observe_objects=False)], [1, 1])
    hidden = scene(observe_objects=False)
    with pytest.raises(ValueError, match="privileged_objects=True does not observe as this env"):
        MixedSceneEnv([hidden, hidden.replace(privileged_objects=True)], [1, 1])


def test_the_curriculum_keeps_the_camera_frames_through_an_advance(rollouts_around_an_advance):
    model = dataclasses.replace(
        TerraShiftModelConfig.small(), camera_channels=1, object_tokens=False
    )
    env, before, after = rollouts_around_an_advance(scene(**LARGE, observe_objects=False), model)
    assert [s.grid_size for s in env.base_env.scenes] == [8, 12]
    assert before["camera"].shape == after["camera"].shape == (4, 2, 1, CAMERA, CAMERA)
    assert "objects" not in after
