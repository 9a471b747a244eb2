"""Shared trunk: shapes, masks, agent permutations and the recurrent-state conventions."""

from __future__ import annotations

import time

import pytest
import torch
from torchrl.envs import Compose, InitTracker, TransformedEnv
from torchrl.modules import set_recurrent_mode

from terrashift_rl.modules import ObjectEncoder, SharedEmbeddingNetwork, TerraShiftTrunk, keys
from terrashift_rl.modules.encodings import sincos_code

ATOL = 1e-5


@pytest.fixture(params=[False, True], ids=["shared-objects", "relative-objects"])
def relative_config(request, small_config):
    small_config.relative_objects = request.param
    return small_config


@pytest.fixture
def trunk(relative_config):
    torch.manual_seed(0)
    # Eval mode: these tests compare outputs, which dropout in grad-enabled passes would perturb.
    return TerraShiftTrunk(relative_config).eval()


@pytest.mark.parametrize(
    ("num_agents", "num_objects", "map_side"),
    [(8, 4, 32), (16, 4, 32), (16, 4, 64), (1, 1, 32), (5, 7, 48)],
)
def test_shapes_for_any_agents_objects_and_map(
    trunk, small_config, make_batch, num_agents, num_objects, map_side
):
    data = make_batch((3,), num_agents=num_agents, num_objects=num_objects, map_side=map_side)
    trunk(data)
    dim, layers = small_config.embed_dim, small_config.gru_layers
    assert data[keys.AGENT_EMBEDDING].shape == (3, num_agents, dim)
    assert data[keys.NEXT_RECURRENT_STATE].shape == (3, num_agents, layers, dim)
    assert data[keys.NEXT_RECURRENT_STATE].dtype == torch.float32
    assert torch.isfinite(data[keys.AGENT_EMBEDDING]).all()


def test_two_batch_dims_in_step_mode(trunk, make_batch):
    data = make_batch((2, 5))
    trunk(data)
    assert data[keys.AGENT_EMBEDDING].shape[:3] == (2, 5, 8)


def test_padded_object_slots_change_nothing(trunk, make_batch):
    data = make_batch((4,), active_objects=2)
    reference = trunk(data.clone())
    data["objects"][:, 2:] = torch.randn(4, 2, 9) * 10
    changed = trunk(data.clone())
    torch.testing.assert_close(changed[keys.AGENT_EMBEDDING], reference[keys.AGENT_EMBEDDING])


def test_no_active_object_gives_finite_embeddings(trunk, make_batch):
    data = make_batch((4,), active_objects=0)
    assert torch.isfinite(trunk(data)[keys.AGENT_EMBEDDING]).all()


def test_absent_agents_do_not_affect_present_ones(trunk, make_batch):
    data = make_batch((4,), num_agents=6, is_init=False)
    data["agents", "mask"][:, [1, 4]] = False
    data["agents", "recurrent_state"] = torch.randn(4, 6, 2, 32)
    reference = trunk(data.clone())
    data["agents", "observation"][:, [1, 4]] = torch.randn(4, 2, 9)
    data["agents", "recurrent_state"][:, [1, 4]] = torch.randn(4, 2, 2, 32)
    changed = trunk(data.clone())
    present = [0, 2, 3, 5]
    torch.testing.assert_close(
        changed[keys.AGENT_EMBEDDING][:, present], reference[keys.AGENT_EMBEDDING][:, present]
    )
    torch.testing.assert_close(
        changed[keys.NEXT_RECURRENT_STATE][:, present],
        reference[keys.NEXT_RECURRENT_STATE][:, present],
    )


def test_permuting_agents_permutes_embeddings_without_agent_id_code(relative_config, make_batch):
    relative_config.agent_id_code = False
    torch.manual_seed(0)
    trunk = TerraShiftTrunk(relative_config).eval()
    data = make_batch((3,), num_agents=5, is_init=False)
    data["agents", "recurrent_state"] = torch.randn(3, 5, 2, 32)
    permutation = torch.tensor([3, 0, 4, 1, 2])
    reference = trunk(data.clone())
    permuted = data.clone()
    permuted["agents"] = data["agents"][:, permutation]
    permuted = trunk(permuted)
    torch.testing.assert_close(
        permuted[keys.AGENT_EMBEDDING],
        reference[keys.AGENT_EMBEDDING][:, permutation],
        atol=ATOL,
        rtol=1e-4,
    )


def test_relative_object_tokens_encode_each_agents_offsets(small_config):
    small_config.relative_objects = True
    torch.manual_seed(0)
    encoder = ObjectEncoder(small_config)
    objects, agents = torch.rand(2, 3, 9) * 2 - 1, torch.rand(2, 5, 9) * 2 - 1
    mask = torch.tensor([[True, True, False], [True, False, True]])
    tokens = encoder(objects, mask, agents)
    assert tokens.shape == (2, 5, 3, small_config.embed_dim)
    for b, k, m in [(0, 0, 0), (0, 4, 1), (1, 2, 2)]:
        offsets = torch.cat(
            [objects[b, m, 0:2] - agents[b, k, 0:2], objects[b, m, 3:5] - agents[b, k, 0:2]]
        )
        short = torch.where(
            offsets > 1, offsets - 2, torch.where(offsets < -1, offsets + 2, offsets)
        )
        inputs = torch.cat([objects[b, m], offsets, short])
        expected = encoder.mlp(inputs) + sincos_code(torch.tensor(m), small_config.embed_dim)
        torch.testing.assert_close(tokens[b, k, m], expected)
    assert tokens[0, :, 2].eq(0).all() and tokens[1, :, 1].eq(0).all()  # padded slots
    # an object just across the wrapped edge from an agent reads as close
    objects[0, 0, 0:2], agents[0, 0, 0:2] = torch.tensor([0.9, 0.0]), torch.tensor([-0.9, 0.0])
    captured = []
    handle = encoder.mlp[0].register_forward_hook(lambda mod, args, out: captured.append(args[0]))
    encoder(objects, mask, agents)
    handle.remove()
    straight, short = captured[0][0, 0, 0, 9:11], captured[0][0, 0, 0, 13:15]
    torch.testing.assert_close(straight, torch.tensor([1.8, 0.0]))
    torch.testing.assert_close(short, torch.tensor([-0.2, 0.0]))
    with pytest.raises(ValueError, match="agents' observations"):
        encoder(objects, mask)


def test_agent_id_code_breaks_permutation_equivariance(trunk, make_batch):
    # Documented behaviour: with the index code on, agent i is told it is agent i.
    data = make_batch((3,), num_agents=5)
    permutation = torch.tensor([3, 0, 4, 1, 2])
    reference = trunk(data.clone())[keys.AGENT_EMBEDDING][:, permutation]
    permuted = data.clone()
    permuted["agents"] = data["agents"][:, permutation]
    assert not torch.allclose(trunk(permuted)[keys.AGENT_EMBEDDING], reference, atol=1e-3)


def test_state_resets_where_episodes_start(trunk, make_batch):
    data = make_batch((4,))
    data["agents", "recurrent_state"] = torch.randn(4, 8, 2, 32)
    data["is_init"] = torch.tensor([[True], [False], [True], [False]])
    carried = trunk(data.clone())
    fresh = data.clone()
    fresh["agents", "recurrent_state"] = torch.zeros(4, 8, 2, 32)
    fresh = trunk(fresh)
    for key in (keys.AGENT_EMBEDDING, keys.NEXT_RECURRENT_STATE):
        torch.testing.assert_close(carried[key][[0, 2]], fresh[key][[0, 2]])
        assert not torch.allclose(carried[key][[1, 3]], fresh[key][[1, 3]], atol=1e-3)


def test_missing_state_means_zeros_at_episode_starts_only(trunk, make_batch):
    data = make_batch((2,))
    without_state = trunk(data.clone())
    data["agents", "recurrent_state"] = torch.zeros(2, 8, 2, 32)
    torch.testing.assert_close(
        trunk(data.clone())[keys.AGENT_EMBEDDING], without_state[keys.AGENT_EMBEDDING]
    )
    del data["is_init"]
    with pytest.raises(KeyError, match="InitTracker"):
        trunk(data.clone())
    mid_episode = make_batch((2,), is_init=False)
    with pytest.raises(KeyError, match="make_tensordict_primer"):
        trunk(mid_episode)


def test_step_by_step_equals_sequence_mode(trunk, make_batch):
    steps = 6
    data = make_batch((3, steps), num_agents=4, is_init=False)
    # Episode starts inside the sequences, and a non-zero state at the first step.
    data["is_init"][0, 0] = True
    data["is_init"][1, 3] = True
    data["is_init"][2, 1] = True
    data["is_init"][2, 4] = True
    start_state = torch.randn(3, 4, 2, 32)

    state = start_state
    step_embeddings, step_states = [], []
    for step in range(steps):
        step_data = data[:, step].clone()
        step_data["agents", "recurrent_state"] = state
        trunk(step_data)
        state = step_data[keys.NEXT_RECURRENT_STATE]
        step_embeddings.append(step_data[keys.AGENT_EMBEDDING])
        step_states.append(state)

    sequence = data.clone()
    # Only the first step's stored state is used in recurrent mode; the rest is ignored.
    sequence["agents", "recurrent_state"] = torch.randn(3, steps, 4, 2, 32)
    sequence["agents", "recurrent_state"][:, 0] = start_state
    with set_recurrent_mode(True):
        trunk(sequence)
    torch.testing.assert_close(
        sequence[keys.AGENT_EMBEDDING], torch.stack(step_embeddings, 1), atol=ATOL, rtol=1e-4
    )
    torch.testing.assert_close(
        sequence[keys.NEXT_RECURRENT_STATE], torch.stack(step_states, 1), atol=ATOL, rtol=1e-4
    )


def test_primer_lets_rollouts_carry_the_state(networks, mock_env_class):
    env = TransformedEnv(
        mock_env_class(2, num_agents=4), Compose(InitTracker(), networks.make_tensordict_primer(4))
    )
    with torch.no_grad():
        rollout = env.rollout(5, networks.actor)
    state = rollout[keys.RECURRENT_STATE]
    assert state.shape == (2, 5, 4, 2, 32)
    assert rollout["is_init"][:, 0].all() and not rollout["is_init"][:, 1:].any()
    assert state[:, 0].eq(0).all()
    # The state read at step t+1 is the one written at step t.
    torch.testing.assert_close(state[:, 1:], rollout[keys.NEXT_RECURRENT_STATE][:, :-1])
    assert state[:, 1:].abs().sum() > 0

    # Replaying the rollout in recurrent mode reproduces the collection-time embeddings.
    replay = rollout.clone()
    with torch.no_grad(), set_recurrent_mode(True):
        networks.trunk(replay)
    torch.testing.assert_close(
        replay[keys.AGENT_EMBEDDING], rollout[keys.AGENT_EMBEDDING], atol=ATOL, rtol=1e-4
    )


def test_collector_carries_the_state(networks, mock_env_class):
    from torchrl.collectors import Collector

    env = TransformedEnv(
        mock_env_class(2, num_agents=3), Compose(InitTracker(), networks.make_tensordict_primer(3))
    )
    collector = Collector(env, networks.actor, frames_per_batch=8, total_frames=8)
    batch = next(iter(collector))
    collector.shutdown()
    assert batch[keys.ACTION].shape == (2, 4, 3, 6)
    torch.testing.assert_close(
        batch[keys.RECURRENT_STATE][:, 1:], batch[keys.NEXT_RECURRENT_STATE][:, :-1]
    )


@pytest.mark.slow  # about 30 s of CPU compilation with a cold inductor cache
def test_forward_under_torch_compile(small_config, make_batch):
    torch.manual_seed(0)
    network = SharedEmbeddingNetwork(small_config).eval()
    data = make_batch((4,), is_init=False)
    data["is_init"][0] = True
    inputs = (data["heightmap"], data["objects"], data["agents", "observation"])
    options = {
        "objects_mask": data["objects_mask"],
        "recurrent_state": torch.randn(4, 8, 2, 32),
        "is_init": data["is_init"],
    }
    start = time.perf_counter()
    compiled = torch.compile(network)
    with torch.no_grad():
        eager_embedding, eager_state = network(*inputs, **options)
        compiled_embedding, compiled_state = compiled(*inputs, **options)
    elapsed = time.perf_counter() - start
    torch.testing.assert_close(compiled_embedding, eager_embedding, atol=1e-4, rtol=1e-4)
    torch.testing.assert_close(compiled_state, eager_state, atol=1e-4, rtol=1e-4)
    assert elapsed < 600
