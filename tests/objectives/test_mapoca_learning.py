"""MA-POCA on a cooperative matrix game where only agent 0's action matters.

Two agents each play 0 or 1 once; the team reward is 1 when agent 0 plays 1, whatever agent 1
does. The counterfactual baseline of agent 1 sees agent 0's action, so it predicts the return
exactly and agent 1's advantage vanishes; agent 0's baseline cannot see agent 0's action, so
agent 0's advantage is its own contribution. The team policy should learn to play 1 with agent 0.
"""

import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule, TensorDictSequential
from torch import nn
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.modules import ProbabilisticActor
from torchrl.objectives import ValueEstimators

from terrashift_rl.objectives import MAPOCALoss

N_AGENTS, N_ACTIONS, EMBED_DIM = 2, 2, 16
EPISODES_PER_UPDATE, EPOCHS, MINIBATCHES = 256, 4, 4


class BaselineHead(nn.Module):
    """b_i from g(e_i) and the mean of f(e_j, onehot(a_j)) over the other agents."""

    def __init__(self) -> None:
        super().__init__()
        self.own = nn.Linear(EMBED_DIM, EMBED_DIM)
        self.others = nn.Linear(EMBED_DIM + N_ACTIONS, EMBED_DIM)
        self.head = nn.Sequential(nn.Tanh(), nn.Linear(EMBED_DIM, 1))

    def forward(self, embedding: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        action = nn.functional.one_hot(action.long(), N_ACTIONS).to(embedding.dtype)
        others = self.others(torch.cat([embedding, action], -1))
        others = (others.sum(-2, keepdim=True) - others) / (N_AGENTS - 1)
        return self.head(self.own(embedding) + others)


class ValueHead(nn.Module):
    def __init__(self) -> None:
        super().__init__()
        self.head = nn.Sequential(nn.Tanh(), nn.Linear(EMBED_DIM, 1))

    def forward(self, embedding: torch.Tensor) -> torch.Tensor:
        return self.head(embedding.mean(-2))


def make_loss(seed: int) -> MAPOCALoss:
    torch.manual_seed(seed)
    # The observation is the agent's one-hot id; the trunk is shared by all three networks.
    trunk = TensorDictModule(
        nn.Linear(N_AGENTS, EMBED_DIM),
        in_keys=[("agents", "observation")],
        out_keys=[("agents", "embedding")],
    )
    policy = TensorDictModule(
        nn.Sequential(nn.Tanh(), nn.Linear(EMBED_DIM, N_ACTIONS)),
        in_keys=[("agents", "embedding")],
        out_keys=[("agents", "logits")],
    )
    actor = ProbabilisticActor(
        TensorDictSequential(trunk, policy),
        in_keys={"logits": ("agents", "logits")},
        out_keys=[("agents", "action")],
        distribution_class=torch.distributions.Categorical,
        return_log_prob=True,
    )
    value = TensorDictModule(
        ValueHead(), in_keys=[("agents", "embedding")], out_keys=["state_value"]
    )
    baseline = TensorDictModule(
        BaselineHead(),
        in_keys=[("agents", "embedding"), ("agents", "action")],
        out_keys=[("agents", "baseline")],
    )
    loss = MAPOCALoss(
        actor, value, baseline, clip_epsilon=0.2, entropy_coeff=0.01, normalize_advantage=False
    )
    return loss.make_value_estimator(ValueEstimators.GAE, gamma=0.99, lmbda=0.95)


def play(actor: ProbabilisticActor, episodes: int) -> TensorDict:
    """One-step episodes of the game, batch [episodes, 1 step]."""
    batch = [episodes, 1]
    observation = torch.eye(N_AGENTS).expand(*batch, N_AGENTS, N_AGENTS)
    data = TensorDict(
        {"agents": TensorDict({"observation": observation}, batch_size=[*batch, N_AGENTS])},
        batch_size=batch,
    )
    with torch.no_grad(), set_exploration_type(ExplorationType.RANDOM):
        actor(data)
    team_reward = (data["agents", "action"][..., 0] == 1).float()
    ended = torch.ones(*batch, 1, dtype=torch.bool)
    data["next"] = TensorDict(
        {
            "agents": TensorDict(
                {
                    "observation": observation,
                    "reward": team_reward[..., None, None].expand(*batch, N_AGENTS, 1),
                },
                batch_size=[*batch, N_AGENTS],
            ),
            "done": ended,
            "terminated": ended,
        },
        batch_size=batch,
    )
    return data


def correlation(x: torch.Tensor, y: torch.Tensor) -> float:
    x, y = x.flatten().float(), y.flatten().float()
    return torch.corrcoef(torch.stack([x, y]))[0, 1].item()


def test_counterfactual_advantages_credit_only_the_agent_that_matters():
    torch.manual_seed(0)
    loss = make_loss(seed=0)
    critics = [*loss.value_network.parameters(), *loss.baseline_network.parameters()]
    optimiser = torch.optim.Adam(critics, lr=0.02)
    # The policy stays at its initial, nearly uniform, parameters; only V and b learn.
    for _ in range(150):
        data = play(loss.actor_network, EPISODES_PER_UPDATE)
        loss.value_estimator(data)
        losses = loss(data)
        optimiser.zero_grad()
        (losses["loss_critic"] + losses["loss_baseline"]).backward()
        optimiser.step()

    data = play(loss.actor_network, 4 * EPISODES_PER_UPDATE)
    loss.value_estimator(data)
    advantage = data["agents", "advantage"].squeeze(-1)
    action = data["agents", "action"]
    assert correlation(advantage[..., 0], action[..., 0]) > 0.95
    assert advantage[..., 1].var() < 0.05 * advantage[..., 0].var()
    assert abs(correlation(advantage[..., 1], action[..., 1])) < 0.2


def test_team_policy_learns_the_game():
    torch.manual_seed(1)
    loss = make_loss(seed=1)
    optimiser = torch.optim.Adam(loss.parameters(), lr=0.01)
    mean_rewards = []
    for _ in range(20):
        data = play(loss.actor_network, EPISODES_PER_UPDATE)
        mean_rewards.append(data["next", "agents", "reward"].mean().item())
        loss.value_estimator(data)
        for _ in range(EPOCHS):
            for minibatch in data.reshape(-1)[torch.randperm(EPISODES_PER_UPDATE)].split(
                EPISODES_PER_UPDATE // MINIBATCHES
            ):
                losses = loss(minibatch)
                optimiser.zero_grad()
                sum(value for key, value in losses.items() if key.startswith("loss_")).backward()
                optimiser.step()

    assert mean_rewards[0] < 0.7
    assert max(mean_rewards[:15]) > 0.95, mean_rewards
    final = play(loss.actor_network, 4 * EPISODES_PER_UPDATE)
    plays_one = (final["agents", "action"] == 1).float().mean(0).squeeze(0)
    assert plays_one[0] > 0.95
    # Agent 1's advantages carry no signal, so nothing pushes its policy away from uniform.
    assert 0.3 < plays_one[1] < 0.7
