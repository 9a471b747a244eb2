"""The trunk with the overhead camera and without the object sequence: learning from pixels."""

from __future__ import annotations

import dataclasses

import pytest
import torch
from test_terrashift_networks import parameters_without_gradient
from torchrl.envs import Compose, InitTracker, TransformedEnv

from terrashift_rl.envs import TerraShiftEnv
from terrashift_rl.modules import keys, make_terrashift_networks
from terrashift_rl.sim.camera import camera_levels

SMOKE_SCENE = {
    "grid_size": 8,
    "num_agents": 4,
    "num_objects": 2,
    "num_goals": 2,
    "spawn_margin": 1,
    "heightmap_resolution": 16,
}


def pixel_networks(small_config, *, camera: bool, objects: bool):
    torch.manual_seed(0)
    config = dataclasses.replace(small_config, camera_channels=int(camera), object_tokens=objects)
    return make_terrashift_networks(config).eval()


def pixel_batch(make_batch, *, camera_side: int | None, objects: bool, batch_shape=(3,)):
    data = make_batch(batch_shape, num_agents=4)
    if camera_side is not None:
        generator = torch.Generator().manual_seed(1)
        data["camera"] = torch.rand(*batch_shape, 1, camera_side, camera_side, generator=generator)
    if not objects:
        del data["objects"], data["objects_mask"]
    return data


@pytest.mark.parametrize(
    ("camera_side", "objects"),
    [(None, True), (32, True), (64, False), (16, False), (None, False)],
    ids=["heightmap", "camera-as-map", "camera-finer", "camera-coarser", "no-objects"],
)
def test_every_parameter_learns_with_and_without_camera_and_objects(
    small_config, make_batch, camera_side, objects
):
    networks = pixel_networks(small_config, camera=camera_side is not None, objects=objects)
    data = pixel_batch(make_batch, camera_side=camera_side, objects=objects, batch_shape=(2, 3))
    data["is_init"][:, 1:] = False
    assert parameters_without_gradient(networks, data) == []
    assert data[keys.STATE_VALUE].shape == (2, 3, 1)
    stem_inputs = networks.trunk.network.heightmap_encoder.stem[0].in_channels
    assert stem_inputs == 1 + (camera_side is not None) + 2  # heightmap, camera, coordinates


def test_the_camera_is_read_and_the_objects_are_not(small_config, make_batch):
    networks = pixel_networks(small_config, camera=True, objects=False)
    trunk = networks.trunk
    assert keys.CAMERA in trunk.in_keys
    assert keys.OBJECTS not in trunk.in_keys and keys.OBJECTS_MASK not in trunk.in_keys
    data = pixel_batch(make_batch, camera_side=32, objects=False)
    with torch.no_grad():
        embedding = trunk(data.clone())[keys.AGENT_EMBEDDING]
        moved = data.clone()
        moved["camera"] = moved["camera"].roll(5, dims=-1)
        assert not torch.allclose(trunk(moved)[keys.AGENT_EMBEDDING], embedding)
        with_objects = pixel_batch(make_batch, camera_side=32, objects=True)
        torch.testing.assert_close(trunk(with_objects)[keys.AGENT_EMBEDDING], embedding)


def test_a_camera_trunk_without_a_camera_is_refused(small_config, make_batch):
    networks = pixel_networks(small_config, camera=True, objects=True)
    with pytest.raises(ValueError, match="camera"):
        networks.trunk(pixel_batch(make_batch, camera_side=None, objects=True))


def test_actor_acts_on_the_environment_from_pixels(small_config):
    networks = pixel_networks(small_config, camera=True, objects=False)
    env = TerraShiftEnv(
        num_envs=2, seed=0, camera_resolution=24, observe_objects=False, **SMOKE_SCENE
    )
    env = TransformedEnv(env, Compose(InitTracker(), networks.make_tensordict_primer(4)))
    with torch.no_grad():
        rollout = env.rollout(3, networks.actor, break_when_any_done=False)
    assert rollout["camera"].shape == (2, 3, 1, 24, 24)
    assert "objects" not in rollout
    actions = rollout[keys.ACTION]
    assert actions.shape == (2, 3, 4, 6) and actions.abs().max() <= 1.0


def test_a_spheres_pixels_reach_the_critics(small_config):
    """The critics share the trunk and see the spheres only through it: the value and every
    baseline have a gradient at the pixels of a rendered sphere."""
    networks = pixel_networks(small_config, camera=True, objects=False)
    env = TerraShiftEnv(
        num_envs=2, seed=0, camera_resolution=24, observe_objects=False, **SMOKE_SCENE
    )
    data = env.reset()
    data["is_init"] = torch.ones(2, 1, dtype=torch.bool)
    data[keys.ACTION] = torch.zeros(2, 4, 6)
    camera = data["camera"].requires_grad_(True)
    sphere_levels = torch.tensor([sphere for _, sphere in camera_levels(2)])
    spheres = torch.isclose(camera.detach()[..., None], sphere_levels).any(-1)
    assert spheres.any()
    networks.baseline_head(networks.value_head(networks.trunk(data)))
    for key in (keys.STATE_VALUE, keys.BASELINE):
        (gradient,) = torch.autograd.grad(data[key].sum(), camera, retain_graph=True)
        assert gradient[spheres].abs().sum() > 0, key
