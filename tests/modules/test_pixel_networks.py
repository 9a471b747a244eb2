"""The trunk with the overhead camera and without the object sequence: learning from pixels;
privileged critics, which read the object sequence the actor never sees."""

from __future__ import annotations

import dataclasses

import pytest
import torch
from test_terrashift_networks import parameters_without_gradient
from torchrl.envs import Compose, InitTracker, TransformedEnv
from torchrl.envs.utils import ExplorationType, set_exploration_type

from terrashift_rl.envs import TerraShiftEnv
from terrashift_rl.modules import TerraShiftModelConfig, keys, make_terrashift_networks
from terrashift_rl.sim.camera import camera_levels

SMOKE_SCENE = {
    "grid_size": 8,
    "num_agents": 4,
    "num_objects": 2,
    "num_goals": 2,
    "spawn_margin": 1,
    "heightmap_resolution": 16,
}


def pixel_networks(small_config, *, camera: bool, objects: bool, critic_objects: bool = False):
    torch.manual_seed(0)
    config = dataclasses.replace(
        small_config,
        camera_channels=int(camera),
        object_tokens=objects,
        critic_objects=critic_objects,
    )
    return make_terrashift_networks(config).eval()


def pixel_batch(
    make_batch,
    *,
    camera_side: int | None,
    objects: bool,
    batch_shape=(3,),
    privileged: bool = False,
):
    """A batch with a camera of ``camera_side`` pixels (None: no camera), the object sequence
    observed (``objects``), handed to the critics alone (``privileged``) or left out."""
    data = make_batch(batch_shape, num_agents=4)
    if camera_side is not None:
        generator = torch.Generator().manual_seed(1)
        data["camera"] = torch.rand(*batch_shape, 1, camera_side, camera_side, generator=generator)
    if privileged:
        data[keys.PRIVILEGED_OBJECTS] = data["objects"]
        data[keys.PRIVILEGED_OBJECTS_MASK] = data["objects_mask"]
    if not objects:
        del data["objects"], data["objects_mask"]
    return data


@pytest.mark.parametrize(
    ("camera_side", "objects", "privileged"),
    [
        (None, True, False),
        (32, True, False),
        (64, False, False),
        (16, False, False),
        (None, False, False),
        (32, False, True),
    ],
    ids=[
        "heightmap",
        "camera-as-map",
        "camera-finer",
        "camera-coarser",
        "no-objects",
        "privileged-critics",
    ],
)
def test_every_parameter_learns_with_and_without_camera_and_objects(
    small_config, make_batch, camera_side, objects, privileged
):
    networks = pixel_networks(
        small_config, camera=camera_side is not None, objects=objects, critic_objects=privileged
    )
    data = pixel_batch(
        make_batch,
        camera_side=camera_side,
        objects=objects,
        batch_shape=(2, 3),
        privileged=privileged,
    )
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


PRIVILEGED_KEYS = {keys.PRIVILEGED_OBJECTS, keys.PRIVILEGED_OBJECTS_MASK}


def test_the_privileged_objects_reach_the_critics_and_never_the_actor(small_config, make_batch):
    networks = pixel_networks(small_config, camera=True, objects=False, critic_objects=True)
    assert not PRIVILEGED_KEYS & {*networks.actor.in_keys, *networks.trunk.in_keys}
    for head in (networks.value_head, networks.baseline_head):
        assert set(head.in_keys) >= PRIVILEGED_KEYS
    data = pixel_batch(make_batch, camera_side=32, objects=False, privileged=True)
    other = data.clone()
    generator = torch.Generator().manual_seed(2)
    other[keys.PRIVILEGED_OBJECTS] = torch.rand(
        other[keys.PRIVILEGED_OBJECTS].shape, generator=generator
    )
    other[keys.PRIVILEGED_OBJECTS_MASK][..., -1] = False
    # the actor's mean action, so that the baselines read the same actions in both
    with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
        seen, other = (
            networks.baseline_head(networks.value_head(networks.actor(batch)))
            for batch in (data, other)
        )
    for key in (keys.BETA_CONCENTRATION1, keys.BETA_CONCENTRATION0, keys.ACTION):
        torch.testing.assert_close(other[key], seen[key], rtol=0, atol=0)
    for key in (keys.STATE_VALUE, keys.BASELINE):
        assert not torch.allclose(other[key], seen[key]), key


def test_privileged_critics_ignore_the_contents_of_empty_slots(small_config, make_batch):
    networks = pixel_networks(small_config, camera=True, objects=False, critic_objects=True)
    data = pixel_batch(make_batch, camera_side=32, objects=False, privileged=True)
    data[keys.PRIVILEGED_OBJECTS_MASK][..., 2:] = False
    other = data.clone()
    other[keys.PRIVILEGED_OBJECTS][..., 2:, :] = 7.0
    with torch.no_grad():
        seen, other = (networks.value_network(batch) for batch in (data, other))
    torch.testing.assert_close(other[keys.STATE_VALUE], seen[keys.STATE_VALUE])


def test_privileged_critics_without_their_objects_are_refused(small_config, make_batch):
    networks = pixel_networks(small_config, camera=True, objects=False, critic_objects=True)
    data = pixel_batch(make_batch, camera_side=32, objects=False)
    with torch.no_grad():
        networks.actor(data)  # the actor reads none of them
        with pytest.raises(KeyError, match=r"critic_objects read \('privileged', 'objects'\)"):
            networks.value_head(data)


def test_privileged_critics_beside_object_tokens_are_refused():
    with pytest.raises(ValueError, match="model.critic_objects=true gives the critics the object"):
        TerraShiftModelConfig(critic_objects=True)
