"""Beta policy: the ScaledBeta distribution and the ProbabilisticActor built on the trunk."""

from __future__ import annotations

import dataclasses
import math

import pytest
import torch
from tensordict.nn import InteractionType, set_interaction_type
from torch.distributions import AffineTransform, Beta, Independent, Normal, TransformedDistribution

from terrashift_rl.modules import ScaledBeta, keys, make_terrashift_networks
from terrashift_rl.sim.types import ACTION_DIM

# Monte Carlo tolerance: 5 standard errors of a 200k-sample mean of log-densities.
MC_SAMPLES = 200_000


@pytest.fixture
def concentrations():
    generator = torch.Generator().manual_seed(0)
    alpha = 1.01 + torch.rand(3, 4, 6, generator=generator) * 4
    beta = 1.01 + torch.rand(3, 4, 6, generator=generator) * 4
    return alpha, beta


def reference_distribution(alpha, beta):
    """torch.distributions' Beta, moved to [-1, 1] by an affine transform, joint over 6 dims."""
    return Independent(TransformedDistribution(Beta(alpha, beta), [AffineTransform(-1.0, 2.0)]), 1)


def test_log_prob_matches_the_transformed_torch_beta(concentrations):
    alpha, beta = concentrations
    dist = ScaledBeta(alpha, beta)
    action = dist.sample()
    assert dist.log_prob(action).shape == (3, 4)
    torch.testing.assert_close(
        dist.log_prob(action), reference_distribution(alpha, beta).log_prob(action)
    )


def test_entropy_is_exact_and_matches_monte_carlo(concentrations):
    alpha, beta = concentrations
    dist = ScaledBeta(alpha, beta)
    expected = Beta(alpha, beta).entropy().sum(-1) + 6 * math.log(2.0)
    torch.testing.assert_close(dist.entropy(), expected)
    torch.manual_seed(0)
    log_probs = dist.log_prob(dist.sample((MC_SAMPLES,)))
    estimate = -log_probs.mean(0)
    standard_error = log_probs.std(0) / math.sqrt(MC_SAMPLES)
    assert ((estimate - dist.entropy()).abs() < 5 * standard_error).all()


def test_mean_is_the_deterministic_sample(concentrations):
    alpha, beta = concentrations
    dist = ScaledBeta(alpha, beta)
    torch.testing.assert_close(dist.mean, 2 * alpha / (alpha + beta) - 1)
    torch.testing.assert_close(dist.deterministic_sample, dist.mean)
    torch.testing.assert_close(dist.mode, 2 * (alpha - 1) / (alpha + beta - 2) - 1)
    torch.manual_seed(0)
    torch.testing.assert_close(dist.sample((50_000,)).mean(0), dist.mean, atol=0.02, rtol=0)


def test_support_is_the_closed_box_and_samples_stay_inside(concentrations):
    alpha, beta = concentrations
    dist = ScaledBeta(alpha, beta)
    samples = dist.sample((1000,))
    assert samples.min() >= -1 and samples.max() <= 1
    assert dist.support.check(samples).all()
    assert not dist.support.check(torch.full((3, 4, 6), 1.5)).any()
    assert dist.event_shape == (6,) and dist.batch_shape == (3, 4)


def test_actions_at_the_ends_of_the_range_have_finite_log_prob(concentrations):
    alpha, beta = concentrations
    dist = ScaledBeta(alpha, beta)
    for end in (-1.0, 1.0):
        log_prob = dist.log_prob(torch.full((3, 4, 6), end))
        assert torch.isfinite(log_prob).all()


def test_rsample_carries_gradients_to_the_concentrations(concentrations):
    alpha, beta = (c.clone().requires_grad_() for c in concentrations)
    ScaledBeta(alpha, beta).rsample().sum().backward()
    assert alpha.grad.abs().sum() > 0 and beta.grad.abs().sum() > 0


def test_actor_writes_action_and_joint_log_prob(networks, make_batch):
    data = make_batch((5,), num_agents=8)
    with torch.no_grad():
        networks.actor(data)
    assert data[keys.ACTION].shape == (5, 8, 6)
    assert data[keys.ACTION].abs().max() <= 1
    assert data[keys.ACTION_LOG_PROB].shape == (5, 8)
    alpha, beta = data[keys.BETA_CONCENTRATION1], data[keys.BETA_CONCENTRATION0]
    assert (alpha >= 1.01).all() and (beta >= 1.01).all()
    expected = ScaledBeta(alpha, beta).log_prob(data[keys.ACTION])
    torch.testing.assert_close(data[keys.ACTION_LOG_PROB], expected)


def test_deterministic_interaction_returns_the_mean(networks, make_batch):
    data = make_batch((5,))
    with torch.no_grad(), set_interaction_type(InteractionType.DETERMINISTIC):
        networks.actor(data)
    mean = ScaledBeta(data[keys.BETA_CONCENTRATION1], data[keys.BETA_CONCENTRATION0]).mean
    torch.testing.assert_close(data[keys.ACTION], mean)


def test_dropout_is_off_during_collection_and_on_in_updates(small_config, make_batch):
    torch.manual_seed(0)
    config = dataclasses.replace(small_config, dropout=0.05)
    networks = make_terrashift_networks(config, action_dim=ACTION_DIM).train()
    data = make_batch((16,))
    with torch.no_grad(), set_interaction_type(InteractionType.RANDOM):
        collected = networks.actor(data.clone())
    with torch.no_grad():
        recomputed = networks.actor.get_dist(data.clone()).log_prob(collected[keys.ACTION])
    # Train mode without autograd (collection, GAE) is deterministic: stored log-probs reproduce.
    torch.testing.assert_close(recomputed, collected[keys.ACTION_LOG_PROB])
    networks.eval()
    evaluated = networks.actor.get_dist(data.clone()).log_prob(collected[keys.ACTION])
    torch.testing.assert_close(evaluated, collected[keys.ACTION_LOG_PROB])
    # Train mode with autograd (the update) applies dropout.
    networks.train()
    updated = networks.actor.get_dist(data.clone()).log_prob(collected[keys.ACTION])
    assert not torch.allclose(updated, collected[keys.ACTION_LOG_PROB], atol=1e-4)


def mean_action(config, data, **overrides):
    """Networks of ``config`` with ``overrides`` (seeded weights) and their mean action."""
    torch.manual_seed(0)
    config = dataclasses.replace(config, **overrides)
    networks = make_terrashift_networks(config, action_dim=ACTION_DIM).eval()
    with torch.no_grad(), set_interaction_type(InteractionType.DETERMINISTIC):
        return networks, networks.actor(data.clone())[keys.ACTION]


def test_action_range_widens_the_policys_support_about_the_same_beta(small_config, make_batch):
    data = make_batch((16,))
    actions = {}
    for span in (1.0, 2.0):
        networks, actions[span] = mean_action(small_config, data, action_range=span)
        dist = networks.actor.get_dist(data.clone())
        assert (dist.low, dist.high) == (-span, span)
    # the same weights and Beta, its support stretched about zero
    torch.testing.assert_close(actions[2.0], 2.0 * actions[1.0])
    with pytest.raises(ValueError, match="model.action_range must be a finite number >= 1"):
        dataclasses.replace(small_config, action_range=0.5)


@pytest.mark.parametrize(("distribution", "span"), [("beta", 1.0), ("beta", 2.0), ("normal", 1.0)])
def test_initial_action_mean_sets_the_untrained_policys_mean_action(
    small_config, make_batch, distribution, span
):
    data = make_batch((4,))
    wanted = [0.0, 0.3, 0.0, -0.1, 0.0, -0.9]
    overrides = {"distribution": distribution, "action_range": span}
    # with zero output weights and the default biases removed, the shift alone sets the
    # distribution: exactly the mean asked
    networks, _ = mean_action(small_config, data, initial_action_mean=wanted, **overrides)
    default, _ = mean_action(small_config, data, **overrides)
    head, centred_head = networks.policy_head.module, default.policy_head.module
    with torch.no_grad():
        for name, layer in head.named_children():
            if isinstance(layer, torch.nn.Linear) and name.endswith("_head"):
                layer.weight.zero_()
                layer.bias.sub_(getattr(centred_head, name).bias)
        mean = networks.actor(data.clone())[keys.ACTION]
    torch.testing.assert_close(mean, torch.tensor(wanted).expand_as(mean))
    # at the default gain, the same shift of the same initial weights
    _, centred = mean_action(small_config, data, **overrides)
    _, shifted = mean_action(small_config, data, initial_action_mean=wanted, **overrides)
    moved = (shifted - centred).mean(dim=(0, 1))
    torch.testing.assert_close(moved, torch.tensor(wanted), atol=0.05, rtol=0.0)


@pytest.mark.parametrize(
    ("value", "message"),
    [
        ([0.0, 0.0, 0.0, -1.0, 0.0, 0.0], "model.initial_action_mean must hold values inside"),
        ([0.0, 0.0, 0.0, math.nan, 0.0, 0.0], "initial_action_mean must be a list of finite"),
        ([0.0, -0.1], r"one value per action dimension \(6\), got 2"),
    ],
)
def test_bad_initial_action_means_are_refused(small_config, value, message):
    with pytest.raises(ValueError, match=message):
        config = dataclasses.replace(small_config, initial_action_mean=value)
        make_terrashift_networks(config, action_dim=ACTION_DIM)


def test_gaussian_policy_samples_about_its_mean_with_one_learned_spread(small_config, make_batch):
    torch.manual_seed(0)
    config = dataclasses.replace(small_config, distribution="normal", initial_std=0.3)
    networks = make_terrashift_networks(config, action_dim=ACTION_DIM)
    data = make_batch((5,), num_agents=8)
    with torch.no_grad():
        networks.actor(data)
    loc, scale = data[keys.NORMAL_LOC], data[keys.NORMAL_SCALE]
    assert loc.shape == scale.shape == data[keys.ACTION].shape == (5, 8, 6)
    torch.testing.assert_close(scale, torch.full_like(scale, 0.3))  # the same in every state
    expected = Independent(Normal(loc, scale), 1).log_prob(data[keys.ACTION])
    torch.testing.assert_close(data[keys.ACTION_LOG_PROB], expected)
    with torch.no_grad(), set_interaction_type(InteractionType.DETERMINISTIC):
        deterministic = networks.actor(data.clone())
    torch.testing.assert_close(deterministic[keys.ACTION], deterministic[keys.NORMAL_LOC])
    # the spread is one parameter per action dim, which the loss trains
    networks.actor.get_dist(data.clone()).log_prob(data[keys.ACTION]).sum().backward()
    log_std = networks.policy_head.module.log_std
    assert log_std.shape == (6,) and (log_std.grad != 0).all()


@pytest.mark.parametrize(
    ("field", "value", "message"),
    [
        ("distribution", "gamma", "distribution must be one of"),
        ("initial_std", 0.0, "initial_std must be a finite number > 0"),
        ("initial_std", math.inf, "initial_std must be a finite number > 0"),
    ],
)
def test_bad_distribution_settings_are_refused(small_config, field, value, message):
    with pytest.raises(ValueError, match=message):
        dataclasses.replace(small_config, **{field: value})
