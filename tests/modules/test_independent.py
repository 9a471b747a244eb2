"""IPPO's per-agent value head: one value per agent, from that agent's embedding alone."""

import torch
from tensordict.nn import TensorDictSequential

from terrashift_rl.modules import AgentValueHead, keys, make_agent_value_head
from terrashift_rl.modules.independent import AGENT_VALUE


def test_each_agents_value_reads_its_own_embedding_only(small_config):
    torch.manual_seed(0)
    head = AgentValueHead(small_config).eval()
    embedding = torch.randn(5, 8, small_config.embed_dim)
    value = head(embedding)
    assert value.shape == (5, 8, 1) and value.dtype == torch.float32
    changed = embedding.clone()
    changed[:, 3] = torch.randn(5, small_config.embed_dim)
    moved = (head(changed) != value).squeeze(-1)
    assert moved[:, 3].all() and not moved[:, [0, 1, 2, 4, 5, 6, 7]].any()
    # the same network for every agent: permuting the agents permutes the values
    order = torch.randperm(8)
    torch.testing.assert_close(head(embedding[:, order]), value[:, order])


def test_the_value_stays_float32_under_bfloat16_autocast(small_config):
    head = AgentValueHead(small_config)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        value = head(torch.randn(2, 4, small_config.embed_dim))
    assert value.dtype == torch.float32


def test_on_the_trunk_it_writes_one_value_per_agent(networks, small_config, make_batch):
    head = make_agent_value_head(small_config)
    critic = TensorDictSequential(networks.trunk, head)
    data = critic(make_batch((3,), num_agents=5))
    assert data[AGENT_VALUE].shape == (3, 5, 1)
    torch.testing.assert_close(
        data[AGENT_VALUE], head.module(data[keys.AGENT_EMBEDDING]), rtol=0, atol=0
    )
    assert networks.config == small_config  # what the trainer sizes the head by
