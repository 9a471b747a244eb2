"""MA-POCA on an environment this project did not write: torchrl's ``MultiAgentCountingEnv``.

Run it (CPU, well under a minute)::

    python examples/mapoca_other_env.py
    python examples/mapoca_other_env.py --iterations 60 --num-envs 8 --seed 1

The mock keeps each agent under its own key, ``("agents", "agent_<i>", ...)``; torchrl's ``Stack``
transform gathers them into one group, ``"team"``, of batch shape [*B, K], the layout
``MAPOCALoss`` reads. Its reward is always zero, so a small transform sets the task: the whole
team earns 1 when agent 0 answers whether the first feature of its observation exceeds 0.5,
whatever the others do. Episodes terminate after ``--episode-steps`` steps, and the done flags
come both at the root and per agent.

Any torchrl multi-agent environment with a stacked group plugs in the same way (VMAS, for
instance, with its group ``"agents"``): build the three networks on its specs, point
``loss.set_keys`` at its group and reward, and keep the training loop.
"""

import argparse

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModule, TensorDictSequential
from torch import nn
from torchrl.collectors import Collector
from torchrl.envs import Compose, EnvBase, SerialEnv, Stack, Transform, TransformedEnv
from torchrl.modules import ProbabilisticActor
from torchrl.objectives import ValueEstimators
from torchrl.testing.mocking_classes import MultiAgentCountingEnv

from terrashift_rl.objectives import MAPOCALoss

GROUP = "team"


class AgentZeroAnswers(Transform):
    """Team reward 1 when agent 0's binary action says whether its first feature exceeds 0.5."""

    def __init__(self, num_agents: int) -> None:
        super().__init__()
        self.num_agents = num_agents

    def _step(self, tensordict: TensorDictBase, next_tensordict: TensorDictBase) -> TensorDictBase:
        # Runs before Stack: the agents still sit under their own keys.
        observation = tensordict.get(("agents", "agent_0", "observation"))
        action = tensordict.get(("agents", "agent_0", "action"))
        answer = (observation[..., :1, 0] > 0.5).to(action.dtype)
        team_reward = (action == answer).to(torch.float32)
        for agent in range(self.num_agents):
            next_tensordict.set(("agents", f"agent_{agent}", "reward"), team_reward.clone())
        return next_tensordict

    def _reset(
        self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase
    ) -> TensorDictBase:
        return tensordict_reset


def make_env(num_agents: int, episode_steps: int) -> EnvBase:
    agents = [("agents", f"agent_{agent}") for agent in range(num_agents)]
    return TransformedEnv(
        MultiAgentCountingEnv(
            n_agents=num_agents, max_steps=episode_steps - 1, env_done_key="done"
        ),
        Compose(
            AgentZeroAnswers(num_agents),
            Stack(in_keys=agents, out_key=GROUP, in_key_inv=GROUP, out_keys_inv=agents),
        ),
    )


class CentralValue(nn.Module):
    """V(s) from the mean of the agents' embeddings."""

    def __init__(self, embed_dim: int) -> None:
        super().__init__()
        self.mlp = nn.Sequential(
            nn.Linear(embed_dim, embed_dim), nn.Tanh(), nn.Linear(embed_dim, 1)
        )

    def forward(self, embedding: torch.Tensor) -> torch.Tensor:
        return self.mlp(embedding.mean(-2))


class CounterfactualBaseline(nn.Module):
    """b_i from agent i's embedding and the mean of (e_j, a_j) over the other agents j."""

    def __init__(self, embed_dim: int, action_dim: int) -> None:
        super().__init__()
        self.own_state = nn.Linear(embed_dim, embed_dim)
        self.other_state_action = nn.Linear(embed_dim + action_dim, embed_dim)
        self.mlp = nn.Sequential(nn.Tanh(), nn.Linear(embed_dim, 1))

    def forward(self, embedding: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        others = self.other_state_action(torch.cat([embedding, action], -1))
        num_others = others.shape[-2] - 1
        others = (others.sum(-2, keepdim=True) - others) / num_others
        return self.mlp(self.own_state(embedding) + others)


def make_loss(env: EnvBase, embed_dim: int) -> MAPOCALoss:
    """Actor, value and baseline sharing one trunk, built from the environment's specs."""
    observation_shape = env.full_observation_spec[GROUP, "observation"].shape[-2:]
    action_dim = env.full_action_spec[GROUP, "action"].shape[-1]
    embedding = (GROUP, "embedding")
    trunk = TensorDictModule(
        nn.Sequential(nn.Flatten(-2), nn.Linear(observation_shape.numel(), embed_dim), nn.Tanh()),
        in_keys=[(GROUP, "observation")],
        out_keys=[embedding],
    )
    policy_head = TensorDictModule(
        nn.Linear(embed_dim, action_dim), in_keys=[embedding], out_keys=[(GROUP, "logits")]
    )
    actor = ProbabilisticActor(
        TensorDictSequential(trunk, policy_head),
        in_keys={"logits": (GROUP, "logits")},
        out_keys=[(GROUP, "action")],
        distribution_class=torch.distributions.Bernoulli,
        return_log_prob=True,
    )
    value = TensorDictModule(CentralValue(embed_dim), in_keys=[embedding], out_keys=["state_value"])
    baseline = TensorDictModule(
        CounterfactualBaseline(embed_dim, action_dim),
        in_keys=[embedding, (GROUP, "action")],
        out_keys=[(GROUP, "baseline")],
    )
    loss = MAPOCALoss(actor, value, baseline, entropy_coeff=0.01, clip_value=0.5)
    # The action and its log-prob keys come from the actor; the rest of the group follows.
    loss.set_keys(group=GROUP)
    return loss.make_value_estimator(ValueEstimators.GAE, gamma=0.5, lmbda=0.95)


def train(
    *,
    iterations: int,
    num_envs: int,
    num_agents: int,
    episode_steps: int,
    steps_per_env: int,
    epochs: int,
    minibatch_size: int,
    seed: int,
) -> list[float]:
    """Trains with MA-POCA; returns the mean team reward per step of every collected batch."""
    torch.manual_seed(seed)
    env = SerialEnv(num_envs, lambda: make_env(num_agents, episode_steps))
    env.set_seed(seed)
    loss = make_loss(env, embed_dim=32)
    optimiser = torch.optim.Adam(loss.parameters(), lr=1e-2)
    collector = Collector(
        env,
        loss.actor_network,
        frames_per_batch=num_envs * steps_per_env,
        total_frames=iterations * num_envs * steps_per_env,
        auto_register_policy_transforms=False,  # feed-forward policy: no recurrent state
    )
    mean_rewards = []
    for iteration, data in enumerate(collector):
        # The batch is [num_envs, steps_per_env]; the pass reads the time dim from its names.
        loss.value_estimator(data)
        team_reward = data["next", GROUP, "reward"].mean().item()
        mean_rewards.append(team_reward)
        samples = data.reshape(-1)
        for _ in range(epochs):
            for minibatch in samples[torch.randperm(samples.numel())].split(minibatch_size):
                losses = loss(minibatch)
                total = sum(value for key, value in losses.items() if key.startswith("loss_"))
                optimiser.zero_grad()
                total.backward()
                nn.utils.clip_grad_norm_(loss.parameters(), 1.0)
                optimiser.step()
        collector.update_policy_weights_()
        print(
            f"iteration {iteration:3d}  mean team reward {team_reward:.3f}  "
            f"entropy {losses['entropy'].item():.3f}  "
            f"explained variance V {losses['explained_variance'].item():+.2f} "
            f"b {losses['explained_variance_baseline'].item():+.2f}"
        )
    collector.shutdown()
    return mean_rewards


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--iterations", type=int, default=40)
    parser.add_argument("--num-envs", type=int, default=4)
    parser.add_argument("--num-agents", type=int, default=3)
    parser.add_argument("--episode-steps", type=int, default=5)
    parser.add_argument("--steps-per-env", type=int, default=50)
    parser.add_argument("--epochs", type=int, default=4)
    parser.add_argument("--minibatch-size", type=int, default=50)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    mean_rewards = train(
        iterations=args.iterations,
        num_envs=args.num_envs,
        num_agents=args.num_agents,
        episode_steps=args.episode_steps,
        steps_per_env=args.steps_per_env,
        epochs=args.epochs,
        minibatch_size=args.minibatch_size,
        seed=args.seed,
    )
    print(f"final mean team reward {mean_rewards[-1]:.3f}")


if __name__ == "__main__":
    main()
