"""MAPOCALoss on a torchrl environment this project did not write, and the example that uses it.

The environment is torchrl's own ``MultiAgentCountingEnv`` with its agents stacked into the group
``"team"`` by torchrl's ``Stack``, as ``examples/mapoca_other_env.py`` builds it.
"""

import importlib.util
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from torchrl.envs import SerialEnv
from torchrl.envs.utils import ExplorationType, set_exploration_type

EXAMPLE = Path(__file__).parents[2] / "examples" / "mapoca_other_env.py"
NUM_AGENTS, EPISODE_STEPS = 3, 4


@pytest.fixture(scope="module")
def example():
    spec = importlib.util.spec_from_file_location("mapoca_other_env", EXAMPLE)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def env(example):
    env = SerialEnv(2, lambda: example.make_env(NUM_AGENTS, EPISODE_STEPS))
    env.set_seed(0)
    yield env
    env.close()


def collect(env, loss, steps: int = 10):
    torch.manual_seed(0)
    with torch.no_grad(), set_exploration_type(ExplorationType.RANDOM):
        return env.rollout(steps, loss.actor_network, break_when_any_done=False)


def test_value_estimation_and_loss_on_a_torchrl_env(example, env):
    loss = example.make_loss(env, embed_dim=8)
    data = collect(env, loss)
    assert data.batch_size == (2, 10) and data.names[-1] == "time"
    assert data["next", "terminated"].any()

    # What in_keys names is all the two passes need (a replay buffer may store just that).
    selected = data.select(*loss.in_keys, strict=False)
    loss.value_estimator(selected)
    loss.value_estimator(data)
    torch.testing.assert_close(loss(selected.reshape(-1)), loss(data.reshape(-1)))
    assert data["value_target"].shape == (2, 10, 1)
    assert data["team", "advantage"].shape == data["team", "baseline"].shape == (2, 10, 3, 1)
    # Termination does not bootstrap: the return of a final step is its reward alone.
    terminated = data["next", "terminated"].squeeze(-1)
    team_reward = data["next", "team", "reward"].mean(-2)
    torch.testing.assert_close(data["value_target"][terminated], team_reward[terminated])

    # The same flags read per agent, in the group, give the same returns.
    per_agent = example.make_loss(env, embed_dim=8)
    per_agent.load_state_dict(loss.state_dict())
    per_agent.set_keys(done=(example.GROUP, "done"), terminated=(example.GROUP, "terminated"))
    per_agent_data = data.exclude("value_target", ("team", "advantage"))
    per_agent.value_estimator(per_agent_data)
    torch.testing.assert_close(per_agent_data["value_target"], data["value_target"])

    losses = loss(data.reshape(-1))
    total = sum(value for key, value in losses.items() if key.startswith("loss_"))
    total.backward()
    assert torch.isfinite(total)
    assert all(p.grad is not None and p.grad.abs().sum() > 0 for p in loss.parameters())


def test_example_runs():
    result = subprocess.run(
        [sys.executable, str(EXAMPLE), "--iterations", "2", "--steps-per-env", "10"],
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert result.returncode == 0, result.stderr
    lines = result.stdout.splitlines()
    assert sum(line.startswith("iteration") for line in lines) == 2
    assert lines[-1].startswith("final mean team reward")
