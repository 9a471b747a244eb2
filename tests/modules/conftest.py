"""Fixtures for the network tests: the small preset, random observation batches, a mock env."""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

from terrashift_rl.modules import TerraShiftModelConfig, make_terrashift_networks

ACTION_DIM = 6


def make_observations(
    batch_shape: tuple[int, ...] = (3,),
    *,
    num_agents: int = 8,
    num_objects: int = 4,
    map_side: int = 32,
    active_objects: int | None = None,
    is_init: bool = True,
    seed: int = 0,
) -> TensorDict:
    """A tensordict following the environment's data contract, with random contents.

    ``active_objects`` slots are active (all by default); agents are all present. Every step is
    an episode start by default, which is when the trunk accepts a missing recurrent state.
    """
    generator = torch.Generator().manual_seed(seed)

    def uniform(*shape: int) -> torch.Tensor:
        return torch.rand(*batch_shape, *shape, generator=generator) * 2 - 1

    objects_mask = torch.zeros(*batch_shape, num_objects, dtype=torch.bool)
    objects_mask[..., : num_objects if active_objects is None else active_objects] = True
    agents = TensorDict(
        {
            "observation": uniform(num_agents, 9),
            "mask": torch.ones(*batch_shape, num_agents, dtype=torch.bool),
            "action": uniform(num_agents, ACTION_DIM),
        },
        [*batch_shape, num_agents],
    )
    return TensorDict(
        {
            "heightmap": uniform(1, map_side, map_side),
            "objects": uniform(num_objects, 9),
            "objects_mask": objects_mask,
            "is_init": torch.full((*batch_shape, 1), is_init),
            "agents": agents,
        },
        list(batch_shape),
    )


class MockTerraShiftEnv(EnvBase):
    """Random observations in TerraShift's layout: heightmap, objects, agents; team done keys."""

    def __init__(
        self, num_envs: int = 2, *, num_agents: int = 4, num_objects: int = 3, map_side: int = 32
    ) -> None:
        super().__init__(batch_size=torch.Size([num_envs]))
        n, k, m = num_envs, num_agents, num_objects
        flags = {
            name: Categorical(2, shape=(n, 1), dtype=torch.bool)
            for name in ("done", "terminated", "truncated")
        }
        agent_flags = {
            name: Categorical(2, shape=(n, k, 1), dtype=torch.bool)
            for name in ("done", "terminated", "truncated")
        }
        self.observation_spec = Composite(
            heightmap=Bounded(-1, 1, shape=(n, 1, map_side, map_side)),
            objects=Bounded(-1, 1, shape=(n, m, 9)),
            objects_mask=Categorical(2, shape=(n, m), dtype=torch.bool),
            agents=Composite(
                observation=Bounded(-1, 1, shape=(n, k, 9)),
                mask=Categorical(2, shape=(n, k), dtype=torch.bool),
                shape=(n, k),
            ),
            shape=(n,),
        )
        self.action_spec = Composite(
            agents=Composite(action=Bounded(-1, 1, shape=(n, k, ACTION_DIM)), shape=(n, k)),
            shape=(n,),
        )
        self.reward_spec = Composite(
            agents=Composite(reward=Unbounded(shape=(n, k, 1)), shape=(n, k)), shape=(n,)
        )
        self.done_spec = Composite(
            **flags, agents=Composite(**agent_flags, shape=(n, k)), shape=(n,)
        )

    def _observe(self) -> TensorDict:
        observation = self.observation_spec.rand()
        observation["objects_mask"].fill_(True)
        observation["agents", "mask"].fill_(True)
        return observation.update(self.full_done_spec.zero())

    def _reset(self, tensordict: TensorDict | None) -> TensorDict:
        return self._observe()

    def _step(self, tensordict: TensorDict) -> TensorDict:
        return self._observe().update(self.full_reward_spec.zero())

    def _set_seed(self, seed: int | None) -> None:
        torch.manual_seed(seed)


@pytest.fixture
def small_config() -> TerraShiftModelConfig:
    return TerraShiftModelConfig.small()


@pytest.fixture
def networks(small_config):
    torch.manual_seed(0)
    # Eval mode so output comparisons are exact; dropout tests switch to train mode themselves.
    return make_terrashift_networks(small_config, action_dim=ACTION_DIM).eval()


@pytest.fixture
def make_batch():
    """The :func:`make_observations` factory (fixtures avoid importing from conftest)."""
    return make_observations


@pytest.fixture
def mock_env_class():
    return MockTerraShiftEnv
