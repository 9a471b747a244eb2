"""Centralised value and counterfactual baselines: the TerraShift heads and the generic critics.

Shapes, masks, permutations over agents, and the errors that name a missing or mis-shaped key.
"""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict
from torch import nn

from terrashift_rl.modules import (
    AttentionBaseline,
    AttentionValue,
    CentralValue,
    CentralValueHead,
    CounterfactualBaseline,
    CounterfactualBaselineHead,
    CounterfactualMLP,
)
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


def assert_same_outputs_and_gradients(network, reference, forward, *inputs) -> torch.Tensor:
    """``forward(network, *inputs)`` gives ``reference``'s outputs and parameter gradients (of
    a weighted sum of the outputs); returns the outputs."""
    outputs = []
    for function in (reference, forward):
        network.zero_grad()
        output = function(network, *inputs)
        (output * torch.linspace(-1, 1, output.numel()).view_as(output)).sum().backward()
        grads = {key: p.grad.clone() for key, p in network.named_parameters()}
        outputs.append((output.detach(), grads))
    (expected, expected_grads), (output, grads) = outputs
    torch.testing.assert_close(output, expected, atol=ATOL, rtol=1e-4)
    for key, grad in expected_grads.items():
        torch.testing.assert_close(grads[key], grad, atol=ATOL, rtol=1e-4, msg=key)
    return output


def k_fold_baseline(network: AttentionBaseline, features, action, agent_mask=None):
    """b_i as the network first computed them: every agent's set materialised as a
    [..., K, K, width] tensor of tokens and passed through the residual self-attention whole."""
    num_agents = features.shape[-2]
    own = network.own_state(features)
    others = network.other_state_action(torch.cat([features, action], -1))
    is_self = torch.eye(num_agents, dtype=torch.bool)
    tokens = torch.where(is_self[..., None], own.unsqueeze(-2), others.unsqueeze(-3))
    key_mask = None if agent_mask is None else agent_mask.unsqueeze(-2) | is_self
    attended = network.attention(tokens, key_mask)
    return network.mlp(masked_mean(attended, key_mask))


@pytest.mark.parametrize("num_agents", [1, 4, 16])
@pytest.mark.parametrize("batch", [(7,), (2, 3)])
@pytest.mark.parametrize("with_mask", [False, True])
def test_baseline_matches_the_k_fold_sets_with_their_gradients(num_agents, batch, with_mask):
    torch.manual_seed(0)
    network = AttentionBaseline(
        nn.Sequential(nn.Linear(5, 16), nn.GELU(), nn.Linear(16, 16)),
        nn.Linear(5 + 2, 16),
        width=16,
        num_heads=4,
        hidden_dim=24,
    )
    generator = torch.Generator().manual_seed(1)
    features = torch.randn(*batch, num_agents, 5, generator=generator)
    action = torch.rand(*batch, num_agents, 2, generator=generator) * 2 - 1
    mask = None
    if with_mask:
        mask = torch.rand(*batch, num_agents, generator=generator) < 0.7
    assert_same_outputs_and_gradients(
        network, k_fold_baseline, AttentionBaseline.forward, features, action, mask
    )


def plain_value(network: AttentionValue, features, agent_mask=None):
    """V as the block computes it: the residual self-attention of layers.py on the set."""
    tokens = network.encoder(features)
    return network.mlp(masked_mean(network.attention(tokens, agent_mask), agent_mask))


# 4 heads: 3 and 8 agents spread keys and values over the heads' channels, 16 do not
@pytest.mark.parametrize("num_agents", [1, 3, 8, 16])
@pytest.mark.parametrize("batch", [(7,), (2, 3)])
@pytest.mark.parametrize("with_mask", [False, True])
def test_value_matches_the_plain_attention_with_its_gradients(num_agents, batch, with_mask):
    torch.manual_seed(0)
    network = AttentionValue(
        nn.Sequential(nn.Linear(5, 16), nn.GELU(), nn.Linear(16, 16)),
        width=16,
        num_heads=4,
        hidden_dim=24,
    )
    generator = torch.Generator().manual_seed(1)
    features = torch.randn(*batch, num_agents, 5, generator=generator)
    mask = None
    if with_mask:
        mask = torch.rand(*batch, num_agents, generator=generator) < 0.7
        mask.view(-1, num_agents)[0] = False  # a team with nobody present
    value = assert_same_outputs_and_gradients(
        network, plain_value, AttentionValue.forward, features, mask
    )
    assert torch.isfinite(value).all()


# --- the generic critics: flat per-agent observations, plain sizes ----------------------------


OBS_DIM, ACTION_DIM = 5, 2


@pytest.mark.parametrize("num_agents", [3, 16])
def test_baseline_encodes_and_projects_each_agent_once(num_agents):
    """What keeps the baselines at a small multiple of the value's cost: the encoders see K
    agents, and the attention's per-token layers 2K tokens (g(x_i) and f(x_j, a_j) once
    each), not the K sets of K tokens."""
    network = CounterfactualBaseline(OBS_DIM, ACTION_DIM, width=8, depth=1, num_heads=2).module
    rows: dict[str, list[int]] = {}

    def count(name):
        def hook(module, inputs, output):
            rows.setdefault(name, []).append(inputs[0].shape[:-1].numel())

        return hook

    attention = network.attention
    layers = {
        "own_state": network.own_state,
        "other_state_action": network.other_state_action,
        "input_norm": attention.input_norm,
        "query_projection": attention.attention.query_projection,
        "key_value_projection": attention.attention.key_value_projection,
    }
    for name, layer in layers.items():
        layer.register_forward_hook(count(name))
    batch = 5
    network(torch.randn(batch, num_agents, OBS_DIM), torch.randn(batch, num_agents, ACTION_DIM))
    assert rows == {
        "own_state": [batch * num_agents],
        "other_state_action": [batch * num_agents],
        "input_norm": [batch * 2 * num_agents],
        "query_projection": [batch * 2 * num_agents],
        "key_value_projection": [batch * 2 * num_agents],
    }


@pytest.fixture
def central_value():
    torch.manual_seed(0)
    return CentralValue(OBS_DIM, width=16, depth=2, num_heads=2).eval()


@pytest.fixture
def counterfactual_baseline():
    torch.manual_seed(0)
    return CounterfactualBaseline(OBS_DIM, ACTION_DIM, width=16, depth=2, num_heads=2).eval()


def team(batch: tuple[int, ...] = (4,), num_agents: int = 5, *, seed: int = 0) -> TensorDict:
    """Observations and actions of a team in VMAS's layout: the group "agents" [*B, K]."""
    generator = torch.Generator().manual_seed(seed)
    agents = TensorDict(
        {
            "observation": torch.randn(*batch, num_agents, OBS_DIM, generator=generator),
            "action": torch.randn(*batch, num_agents, ACTION_DIM, generator=generator),
        },
        [*batch, num_agents],
    )
    return TensorDict({"agents": agents}, list(batch))


@pytest.mark.parametrize("num_agents", [1, 3, 7])
@pytest.mark.parametrize("batch", [(4,), (2, 3)])
def test_generic_critics_write_their_keys_with_the_loss_shapes(
    central_value, counterfactual_baseline, num_agents, batch
):
    data = team(batch, num_agents)
    # the same weights take any number of agents and write into the caller's tensordict
    assert central_value(data) is data
    counterfactual_baseline(data)
    assert data["state_value"].shape == (*batch, 1)
    assert data["agents", "baseline"].shape == (*batch, num_agents, 1)


def test_generic_critics_are_permutation_invariant_and_equivariant_over_agents(
    central_value, counterfactual_baseline
):
    data = team()
    data["agents", "mask"] = torch.tensor([True, False, True, True, True]).expand(4, 5)
    permutation = torch.tensor([3, 0, 4, 1, 2])
    permuted = data.clone()
    permuted["agents"] = data["agents"][:, permutation]
    torch.testing.assert_close(
        central_value(permuted)["state_value"],
        central_value(data)["state_value"],
        atol=ATOL,
        rtol=1e-4,
    )
    torch.testing.assert_close(
        counterfactual_baseline(permuted)["agents", "baseline"],
        counterfactual_baseline(data)["agents", "baseline"][:, permutation],
        atol=ATOL,
        rtol=1e-4,
    )


def test_generic_critics_ignore_absent_agents(central_value, counterfactual_baseline):
    data = team()
    data["agents", "mask"] = torch.tensor([True, True, False, True, False]).expand(4, 5)
    value = central_value(data.clone())["state_value"]
    baseline = counterfactual_baseline(data.clone())["agents", "baseline"]
    garbage = team(seed=1)
    for key in ("observation", "action"):
        data["agents", key][:, [2, 4]] = 10 * garbage["agents", key][:, [2, 4]]
    torch.testing.assert_close(central_value(data)["state_value"], value)
    present = [0, 1, 3]
    torch.testing.assert_close(
        counterfactual_baseline(data)["agents", "baseline"][:, present], baseline[:, present]
    )
    # a mask [*B, K, 1], as the loss also accepts, reads the same
    data["agents", "mask"] = data["agents", "mask"].unsqueeze(-1).float()
    torch.testing.assert_close(central_value(data)["state_value"], value)


def test_generic_baseline_of_an_agent_ignores_its_own_action_only(counterfactual_baseline):
    data = team()
    baseline = counterfactual_baseline(data.clone())["agents", "baseline"]
    data["agents", "action"][:, 1] += 1.0
    changed = counterfactual_baseline(data)["agents", "baseline"]
    torch.testing.assert_close(changed[:, 1], baseline[:, 1])
    others = [0, 2, 3, 4]
    assert not torch.allclose(changed[:, others], baseline[:, others], atol=1e-4)


def test_generic_baseline_one_hot_encodes_integer_actions():
    torch.manual_seed(0)
    baseline = CounterfactualBaseline(OBS_DIM, 3, width=8, depth=1, num_heads=2)
    data = team()
    action = torch.randint(3, (4, 5))
    data["agents", "action"] = action
    one_hot = data.clone()
    one_hot["agents", "action"] = torch.nn.functional.one_hot(action, 3).float()
    torch.testing.assert_close(
        baseline(data)["agents", "baseline"], baseline(one_hot)["agents", "baseline"]
    )
    assert data["agents", "action"].dtype == torch.int64  # the caller's action is left as it was


def test_generic_critics_keys_and_sizes_are_configurable():
    value = CentralValue(3, group="team", out_key=("team", "value"), width=8, num_heads=1)
    baseline = CounterfactualBaseline(3, 2, group="team", action_key=("team", "move"), width=8)
    assert value.in_keys == [("team", "observation"), ("team", "mask")]
    assert value.out_keys == [("team", "value")]
    assert baseline.in_keys == [("team", "observation"), ("team", "move"), ("team", "mask")]
    assert baseline.out_keys == [("team", "baseline")]
    hidden = [layer for layer in value.module.mlp if isinstance(layer, torch.nn.Linear)]
    assert [layer.out_features for layer in hidden] == [8, 8, 1]  # depth 2 hidden layers, then 1


@pytest.mark.parametrize(
    ("change", "error", "message"),
    [
        (lambda data: data["agents"].del_("observation"), KeyError, "'observation'.*5"),
        (
            lambda data: data.set(("agents", "observation"), torch.randn(4, 5, 6)),
            ValueError,
            r"'observation'.*\[\*B, K, 5\].*\[4, 5, 6\]",
        ),
        (lambda data: data["agents"].del_("action"), KeyError, r"'action'.*\[\*B, K, 2\]"),
        (
            lambda data: data.set(("agents", "action"), torch.randn(4, 5, 3)),
            ValueError,
            r"'action'.*\[\*B, K, 2\].*\[4, 5, 3\]",
        ),
        (
            lambda data: data.set(("agents", "mask"), torch.ones(4, 5, 2, dtype=torch.bool)),
            ValueError,
            r"'mask'.*\[\*B, K\] = \[4, 5\].*\[4, 5, 2\]",
        ),
    ],
)
def test_generic_critics_name_a_missing_or_mis_shaped_input(
    counterfactual_baseline, change, error, message
):
    data = team()
    change(data)
    with pytest.raises(error, match=message):
        counterfactual_baseline(data)


def test_terrashift_heads_are_the_generic_networks_on_embeddings(value_head, baseline_head):
    assert isinstance(value_head, AttentionValue) and isinstance(baseline_head, AttentionBaseline)
    embedding, _ = agent_inputs()
    # the value head's encoder is the identity: the trunk already embeds every agent
    torch.testing.assert_close(value_head.encoder(embedding), embedding)


# --- the MLP baseline ----------------------------------------------------------------------


@pytest.fixture
def mlp_baseline():
    torch.manual_seed(0)
    baseline = CounterfactualMLP(5, OBS_DIM, ACTION_DIM, width=16, depth=2)
    nn.init.normal_(baseline.module.agent)  # agent vectors start at zero: make them count
    return baseline


def test_mlp_baseline_is_one_mlp_per_agent_on_the_team_without_its_action(mlp_baseline):
    data = team((2, 3))
    network = mlp_baseline.module
    observation, action = data["agents", "observation"], data["agents", "action"]
    expected = []
    for i in range(5):  # the plain reading: agent i's own action zeroed, its vector added
        others = action.clone()
        others[..., i, :] = 0.0
        flat = torch.cat([observation.flatten(-2), others.flatten(-2)], -1)
        expected.append(network.head(network.team(flat) + network.agent[i]))
    baseline = mlp_baseline(data)["agents", "baseline"]
    assert baseline.shape == (2, 3, 5, 1)
    torch.testing.assert_close(baseline, torch.stack(expected, -2), atol=ATOL, rtol=1e-4)


def test_mlp_baseline_of_an_agent_ignores_its_own_action_only(mlp_baseline):
    data = team()
    baseline = mlp_baseline(data.clone())["agents", "baseline"]
    data["agents", "action"][:, 1] += 1.0
    changed = mlp_baseline(data)["agents", "baseline"]
    torch.testing.assert_close(changed[:, 1], baseline[:, 1])
    assert not torch.allclose(changed[:, [0, 2, 3, 4]], baseline[:, [0, 2, 3, 4]], atol=1e-4)


def test_mlp_baseline_ignores_absent_agents_and_one_hot_encodes_integer_actions():
    torch.manual_seed(0)
    baseline = CounterfactualMLP(5, OBS_DIM, 3, width=8, depth=1)
    data = team()
    data["agents", "action"] = torch.randint(3, (4, 5))
    data["agents", "mask"] = torch.tensor([True, True, False, True, False]).expand(4, 5)
    expected = baseline(data.clone())["agents", "baseline"]
    data["agents", "observation"][:, [2, 4]] = 100.0
    data["agents", "action"][:, [2, 4]] = 2
    torch.testing.assert_close(baseline(data)["agents", "baseline"], expected)


def test_mlp_baseline_names_a_team_of_another_size(mlp_baseline):
    with pytest.raises(ValueError, match=r"built for 5 agents.*'observation'.*holds 3"):
        mlp_baseline(team(num_agents=3))
    data = team()
    data["agents"].del_("observation")
    with pytest.raises(KeyError, match=r"CounterfactualMLP reads .*'observation'"):
        mlp_baseline(data)
    with pytest.raises(ValueError, match="at least one hidden layer"):
        CounterfactualMLP(5, OBS_DIM, ACTION_DIM, depth=0)
