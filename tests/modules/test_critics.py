"""Centralised value and counterfactual baseline heads: shapes, masks, permutations."""

from __future__ import annotations

import pytest
import torch

from terrashift_rl.modules import CentralValueHead, CounterfactualBaselineHead
from terrashift_rl.modules.layers import masked_mean

ATOL = 1e-5


@pytest.fixture
def value_head(small_config):
    torch.manual_seed(0)
    return CentralValueHead(small_config).eval()


@pytest.fixture
def baseline_head(small_config):
    torch.manual_seed(0)
    return CounterfactualBaselineHead(small_config, action_dim=6).eval()


def agent_inputs(batch: int = 4, num_agents: int = 6, dim: int = 32, seed: int = 0):
    generator = torch.Generator().manual_seed(seed)
    embedding = torch.randn(batch, num_agents, dim, generator=generator)
    action = torch.rand(batch, num_agents, 6, generator=generator) * 2 - 1
    return embedding, action


@pytest.mark.parametrize("num_agents", [1, 8, 16])
def test_shapes(value_head, baseline_head, num_agents):
    embedding, action = agent_inputs(num_agents=num_agents)
    assert value_head(embedding).shape == (4, 1)
    assert baseline_head(embedding, action).shape == (4, num_agents, 1)
    assert value_head(embedding.unsqueeze(0).expand(2, -1, -1, -1)).shape == (2, 4, 1)


def test_absent_agents_change_neither_value_nor_other_baselines(value_head, baseline_head):
    embedding, action = agent_inputs()
    mask = torch.ones(4, 6, dtype=torch.bool)
    mask[:, [0, 3]] = False
    value = value_head(embedding, mask)
    baseline = baseline_head(embedding, action, mask)
    embedding[:, [0, 3]] = torch.randn(4, 2, 32) * 5
    action[:, [0, 3]] = torch.rand(4, 2, 6) * 2 - 1
    torch.testing.assert_close(value_head(embedding, mask), value)
    present = [1, 2, 4, 5]
    torch.testing.assert_close(
        baseline_head(embedding, action, mask)[:, present], baseline[:, present]
    )


def test_permuting_agents_leaves_value_and_permutes_baselines(value_head, baseline_head):
    embedding, action = agent_inputs()
    mask = torch.ones(4, 6, dtype=torch.bool)
    mask[:, 2] = False
    permutation = torch.tensor([5, 2, 0, 1, 4, 3])
    torch.testing.assert_close(
        value_head(embedding[:, permutation], mask[:, permutation]),
        value_head(embedding, mask),
        atol=ATOL,
        rtol=1e-4,
    )
    torch.testing.assert_close(
        baseline_head(embedding[:, permutation], action[:, permutation], mask[:, permutation]),
        baseline_head(embedding, action, mask)[:, permutation],
        atol=ATOL,
        rtol=1e-4,
    )


def test_baseline_of_an_agent_ignores_its_own_action(baseline_head):
    embedding, action = agent_inputs()
    baseline = baseline_head(embedding, action)
    changed = action.clone()
    changed[:, 2] = -action[:, 2]
    changed_baseline = baseline_head(embedding, changed)
    torch.testing.assert_close(changed_baseline[:, 2], baseline[:, 2])
    others = [0, 1, 3, 4, 5]
    assert not torch.allclose(changed_baseline[:, others], baseline[:, others], atol=1e-4)


def test_batched_baseline_equals_one_set_per_agent(baseline_head):
    embedding, action = agent_inputs(num_agents=5)
    mask = torch.tensor([True, True, False, True, True]).expand(4, 5)
    batched = baseline_head(embedding, action, mask)
    own = baseline_head.own_state(embedding)
    others = baseline_head.other_state_action(torch.cat([embedding, action], -1))
    for agent in range(5):
        members = [j for j in range(5) if j != agent and mask[0, j]]
        tokens = torch.cat([own[:, agent : agent + 1], others[:, members]], dim=1)
        expected = baseline_head.mlp(masked_mean(baseline_head.attention(tokens), None))
        torch.testing.assert_close(batched[:, agent], expected, atol=ATOL, rtol=1e-4)
