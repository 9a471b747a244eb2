"""mapoca_slow_start.py: the diagnostic variants change what they say and nothing else."""

import sys
from pathlib import Path

import torch
from torchrl.envs.utils import ExplorationType, set_exploration_type

sys.path.insert(0, str(Path(__file__).parents[2] / "benchmarks"))

from mapoca_slow_start import ConcatenatedBaseline, example, make_loss  # noqa: E402


def test_concatenated_baseline_of_an_agent_ignores_its_own_action():
    torch.manual_seed(0)
    baseline = ConcatenatedBaseline(3, observation_dim=4, action_dim=2, width=8, depth=1)
    observation, action = torch.randn(5, 3, 4), torch.randn(5, 3, 2)
    changed = action.clone()
    changed[:, 1] += 1.0
    before, after = baseline(observation, action), baseline(observation, changed)
    assert before.shape == (5, 3, 1)
    torch.testing.assert_close(after[:, 1], before[:, 1])
    assert not torch.allclose(after[:, 0], before[:, 0])
    assert not torch.allclose(after[:, 2], before[:, 2])


def _collected(loss, env, steps: int = 6):
    with torch.no_grad(), set_exploration_type(ExplorationType.RANDOM):
        return env.rollout(steps, loss.actor_network, break_when_any_done=False)


def test_value_advantage_gives_every_agent_the_standardised_central_advantage():
    torch.manual_seed(0)
    env = example.TeamNavigationEnv(4, num_agents=3, episode_steps=5)
    actor = example.make_actor(env, width=8, depth=1)
    made = []
    loss = make_loss("value-advantage", made)(env, actor, width=8, depth=2)
    loss.make_value_estimator(loss.default_value_estimator, gamma=0.9, lmbda=0.9)
    data = loss.value_estimator(_collected(loss, env))
    advantage = data["agents", "advantage"]
    central = (data["value_target"] - data["state_value"]).unsqueeze(-2).expand_as(advantage)
    expected = (central - central.mean()) / central.std(unbiased=False)
    torch.testing.assert_close(advantage, expected)
    assert (advantage == advantage[..., :1, :]).all()  # the same for every agent
    record = made[-1].value_estimator.record
    assert [len(values) for values in record.values()] == [1, 1, 1]


def test_attention_variant_keeps_the_counterfactual_advantage():
    torch.manual_seed(0)
    env = example.TeamNavigationEnv(4, num_agents=3, episode_steps=5)
    actor = example.make_actor(env, width=8, depth=1)
    loss = make_loss("attention", [])(env, actor, width=8, depth=2)
    loss.make_value_estimator(loss.default_value_estimator, gamma=0.9, lmbda=0.9)
    data = loss.value_estimator(_collected(loss, env))
    counterfactual = data["value_target"].unsqueeze(-2) - data["agents", "baseline"]
    expected = (counterfactual - counterfactual.mean()) / counterfactual.std(unbiased=False)
    torch.testing.assert_close(data["agents", "advantage"], expected)
