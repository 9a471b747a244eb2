"""The MAPOCA-beside-MAPPO example: its team-navigation environment and the script itself."""

import importlib.util
import json
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from tensordict import TensorDict
from torch import nn
from torchrl.envs.utils import check_env_specs

from terrashift_rl.modules import CounterfactualMLP

EXAMPLE = Path(__file__).parents[2] / "examples" / "mapoca_vs_mappo.py"
STEP_SIZE = 0.1


@pytest.fixture(scope="module")
def example():
    spec = importlib.util.spec_from_file_location("mapoca_vs_mappo", EXAMPLE)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.fixture
def env(example):
    env = example.TeamNavigationEnv(3, num_agents=2, episode_steps=3, step_size=STEP_SIZE)
    env.set_seed(0)
    return env


def test_team_navigation_specs_match_its_data(env):
    check_env_specs(env)


def test_team_navigation_rewards_the_team_with_the_mean_distance_to_go(env):
    data = env.reset()
    offset = data["agents", "observation"][..., 2:]
    distance = offset.norm(dim=-1)
    # every agent heads straight for its goal (inside the square, so never clamped)
    data["agents", "action"] = offset / distance.unsqueeze(-1)
    after = env.step(data)["next"]
    expected = -(distance - STEP_SIZE).abs().mean(-1, keepdim=True)
    reward = after["agents", "reward"]
    assert reward.shape == (3, 2, 1)
    torch.testing.assert_close(reward, expected.unsqueeze(-1).expand(3, 2, 1))
    torch.testing.assert_close(after["agents", "observation"][..., :2], env.position)


def test_team_navigation_truncates_episodes_and_resets_only_those_asked(env):
    data = env.reset()
    for step in range(3):
        data["agents", "action"] = torch.zeros(3, 2, 2)
        data = env.step(data)
        truncated = step == 2
        assert (data["next", "done"] == truncated).all()
        assert not data["next", "terminated"].any()
        data = data["next"]
    position, goal = env.position.clone(), env.goal.clone()
    env.reset(TensorDict({"_reset": torch.tensor([[False], [True], [False]])}, [3]))
    kept = [0, 2]
    torch.testing.assert_close(env.position[kept], position[kept])
    torch.testing.assert_close(env.goal[kept], goal[kept])
    assert not torch.equal(env.position[1], position[1]) and (env.steps[1] == 0).all()
    assert (env.steps[kept] == 3).all()


def test_unknown_environment_is_refused(example):
    with pytest.raises(ValueError, match="team_navigation or vmas:<scenario>"):
        example.make_env("navigation", num_envs=2, episode_steps=3, seed=0)
    with pytest.raises(ValueError, match="team_navigation runs on the CPU, got device 'cuda'"):
        example.make_env("team_navigation", num_envs=2, episode_steps=3, seed=0, device="cuda")


def test_mapoca_critics_split_the_hidden_layers_of_mappos_critic_around_the_attention(example):
    env = example.TeamNavigationEnv(2, num_agents=3)
    actor = example.make_actor(env, width=8, depth=2)

    def hidden_layers(mlp: nn.Module) -> int:
        return sum(isinstance(layer, nn.Linear) for layer in mlp.modules()) - 1

    mappo_critic = example.make_mappo_loss(env, actor, width=8, depth=2).critic_network
    assert hidden_layers(mappo_critic) == 2
    for depth, each in ((2, 1), (4, 2), (1, 1)):
        loss = example.make_mapoca_loss(env, actor, width=8, depth=depth)
        value, baseline = loss.value_network.module, loss.baseline_network.module
        assert hidden_layers(value.encoder) == hidden_layers(value.mlp) == each
        assert hidden_layers(baseline.own_state) == hidden_layers(baseline.mlp) == each
        assert hidden_layers(baseline.other_state_action) == each


def test_mapoca_can_take_mappos_critic_network_as_its_value(example):
    env = example.TeamNavigationEnv(2, num_agents=3)
    env.set_seed(0)
    actor = example.make_actor(env, width=8, depth=1)
    mappo_critic = example.make_mappo_loss(env, actor, width=8, depth=2).critic_network
    loss = example.make_mapoca_loss(env, actor, width=8, depth=2, value_network="mlp")
    mlp = loss.value_network.module[0]
    assert type(mlp) is type(mappo_critic.module)
    mlp.load_state_dict(mappo_critic.module.state_dict())
    data = env.rollout(3, actor)
    per_agent = mappo_critic(data.clone()).get(("agents", "state_value"))
    team = loss.value_network(data.clone()).get("state_value")
    # the centralised MLP gives every agent the same value: the team's
    torch.testing.assert_close(per_agent, team.unsqueeze(-2).expand_as(per_agent))
    with pytest.raises(ValueError, match="value_network must be 'attention' or 'mlp'"):
        example.make_mapoca_loss(env, actor, width=8, depth=2, value_network="gru")


def test_mapoca_can_take_mlp_baselines_as_wide_and_deep_as_mappos_critic(example):
    env = example.TeamNavigationEnv(2, num_agents=3)
    env.set_seed(0)
    actor = example.make_actor(env, width=8, depth=1)
    loss = example.make_mapoca_loss(
        env, actor, width=8, depth=2, value_network="mlp", baseline_network="mlp"
    )
    baseline = loss.baseline_network
    assert isinstance(baseline, CounterfactualMLP) and baseline.num_agents == 3
    widths = [layer.out_features for layer in baseline.module.head if isinstance(layer, nn.Linear)]
    assert baseline.module.team.out_features == 8 and widths == [8, 1]  # two hidden layers
    with torch.no_grad():
        data = env.rollout(3, actor)
    assert loss(data)["loss_baseline"].isfinite()
    with pytest.raises(ValueError, match="baseline_network must be 'attention' or 'mlp'"):
        example.make_mapoca_loss(env, actor, width=8, depth=2, baseline_network="gru")


@pytest.mark.parametrize("method", ["MAPOCA", "MAPPO"])
def test_critic_width_sizes_both_methods_critics_and_leaves_the_actor(example, monkeypatch, method):
    built = {}
    monkeypatch.setattr(
        example, "train", lambda loss, env, **options: built.setdefault("loss", loss)
    )
    options = ["--width", "8", "--critic-width", "12", "--critic-depth", "2"]
    args = example.parse_args([*options, "--value-network", "mlp", "--baseline-network", "mlp"])
    example.run(method, env_name="team_navigation", seed=0, args=args)
    loss = built["loss"]

    def widths(module: nn.Module) -> set[int]:
        return {layer.out_features for layer in module.modules() if isinstance(layer, nn.Linear)}

    assert widths(loss.actor_network) == {8, 4}  # hidden layers and the two Normal parameters
    critics = (
        [loss.critic_network] if method == "MAPPO" else [loss.value_network, loss.baseline_network]
    )
    assert all(widths(critic) == {12, 1} for critic in critics)


@pytest.mark.parametrize("flag", [[], ["--least-variance-weight"]])
def test_least_variance_weight_reaches_mapocas_loss(example, monkeypatch, flag):
    built = {}
    monkeypatch.setattr(
        example, "train", lambda loss, env, **options: built.setdefault("loss", loss)
    )
    example.run("MAPOCA", env_name="team_navigation", seed=0, args=example.parse_args(flag))
    assert built["loss"].least_variance_weight is bool(flag)


def test_example_trains_both_losses_and_writes_the_table(tmp_path):
    output = tmp_path / "results.json"
    options = ["--iterations", "2", "--num-envs", "4", "--episode-steps", "5"]
    options += ["--minibatch-size", "10", "--seeds", "0", "1", "--json", str(output)]
    result = subprocess.run(
        [sys.executable, str(EXAMPLE), *options],
        capture_output=True,
        text=True,
        timeout=300,
        check=False,
    )
    assert result.returncode == 0, result.stderr
    lines = result.stdout.splitlines()
    assert lines[0].startswith("team_navigation: mean team reward per step")
    assert [line.split()[0] for line in lines[2:]] == ["MAPOCA", "MAPPO"]
    results = json.loads(output.read_text())
    for method in ("MAPOCA", "MAPPO"):
        assert len(results["table"][method]["finals"]) == 2
        curves = results["curves"][method]
        assert sorted(curves) == ["0", "1"] and all(len(curve) == 2 for curve in curves.values())
        # the reward is minus a mean distance on the square [-1, 1]²
        assert all(-2 * 2**0.5 <= reward <= 0 for curve in curves.values() for reward in curve)


def test_counterfactual_warmup_moves_the_weight_from_0_to_1(example):
    env = example.TeamNavigationEnv(4, num_agents=2, episode_steps=5)
    env.set_seed(0)
    actor = example.make_actor(env, width=8, depth=1)
    loss = example.make_mapoca_loss(env, actor, width=8, depth=1)
    weights = []
    estimator = loss.value_estimator
    loss.make_value_estimator = lambda *args, **kwargs: None  # keep the recording estimator

    def recording_estimator(data, **kwargs):
        weights.append(loss.counterfactual_weight.item())
        return estimator(data, **kwargs)

    loss._value_estimator = recording_estimator
    example.train(
        loss, env, iterations=4, frames_per_batch=20, epochs=1, minibatch_size=10, lr=1e-3,
        gamma=0.9, lmbda=0.9, counterfactual_warmup=2,
    )  # fmt: skip
    assert weights == [0.0, 0.5, 1.0, 1.0]
