"""MAPOCALoss beside torchrl's MAPPOLoss on a continuous-action team task, same loop for both.

Run it (CPU)::

    python examples/mapoca_vs_mappo.py                      # TeamNavigationEnv, seed 0
    python examples/mapoca_vs_mappo.py --seeds 0 1 2 --iterations 60 --json results.json
    pip install vmas                                        # then any VMAS scenario:
    python examples/mapoca_vs_mappo.py --env vmas:balance --num-envs 60 --episode-steps 100 \\
        --iterations 100 --seeds 0 1 2 3 4 5 --json balance.json
    python examples/mapoca_vs_mappo.py --env vmas:balance --agents 8 ...  # a larger team

The default task, :class:`TeamNavigationEnv`, is pure torch: K agents on a plane, each steering
to a goal of its own, and one reward for the whole team, the mean distance still to go. Every
agent's reward thus carries the others' progress too; the counterfactual baselines of MA-POCA
are meant to take that noise out of each agent's advantage. With ``--env vmas:<scenario>`` the
same comparison runs on a VMAS scenario (``pip install vmas``; not a dependency of the
package).

Both losses get the same actor, the same hyperparameters and the same training loop, written as
torchrl's MAPPO example writes it: a ``Collector``, the value-estimation call with
``params=loss.critic_network_params``, and the sum of every ``loss_*`` term. MAPOCALoss gets
the generic critics of ``terrashift_rl.modules``; MAPPOLoss its usual centralised
``MultiAgentMLP`` critic, one value per agent (``--value-network mlp`` gives MA-POCA that network
as its value: the better one where the team's reward follows one shared object;
``--baseline-network mlp`` baselines of the same kind, cheaper than the attention). The script
prints a table, method by method, of the mean team reward per step over the last
``--final-iterations`` collected batches (mean ± sd over seeds), and writes the curves to
``--json``.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModule
from torch import nn
from torchrl.collectors import Collector
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase
from torchrl.modules import MultiAgentMLP, NormalParamExtractor, ProbabilisticActor, TanhNormal
from torchrl.objectives import LossModule
from torchrl.objectives.multiagent import MAPPOLoss

from terrashift_rl.modules import (
    CentralValue,
    CounterfactualBaseline,
    CounterfactualMLP,
    mlp_value,
)
from terrashift_rl.objectives import MAPOCALoss

GROUP = "agents"
OBSERVATION, ACTION, REWARD = (GROUP, "observation"), (GROUP, "action"), (GROUP, "reward")


class TeamNavigationEnv(EnvBase):
    """K agents on the square [-1, 1]², each steering to its own goal; one reward for the team.

    Agent i observes its position and its goal's offset, ``[x_i, y_i, gx_i - x_i, gy_i - y_i]``,
    and moves by ``step_size`` times its action, a velocity in [-1, 1]². Every agent gets the
    team reward, minus the mean distance from the agents to their goals after the step. Episodes
    are truncated after ``episode_steps`` steps; starts and goals are uniform on the square.
    The keys are VMAS's: group ``"agents"``, per-agent rewards, team done flags.

    Args:
        num_envs: environments, the batch dim.

    Keyword Args:
        num_agents: K.
        episode_steps: steps before an episode is truncated.
        step_size: distance an action of norm 1 moves an agent.
    """

    def __init__(
        self,
        num_envs: int = 32,
        *,
        num_agents: int = 3,
        episode_steps: int = 20,
        step_size: float = 0.1,
    ) -> None:
        super().__init__(batch_size=torch.Size([num_envs]))
        n, k = num_envs, num_agents
        self.episode_steps = episode_steps
        self.step_size = step_size
        self.observation_spec = Composite(
            {GROUP: Composite(observation=Unbounded(shape=(n, k, 4)), shape=(n, k))}, shape=(n,)
        )
        self.action_spec = Composite(
            {GROUP: Composite(action=Bounded(-1.0, 1.0, shape=(n, k, 2)), shape=(n, k))},
            shape=(n,),
        )
        self.reward_spec = Composite(
            {GROUP: Composite(reward=Unbounded(shape=(n, k, 1)), shape=(n, k))}, shape=(n,)
        )
        self.done_spec = Composite(
            {
                name: Categorical(2, shape=(n, 1), dtype=torch.bool)
                for name in ("done", "terminated", "truncated")
            },
            shape=(n,),
        )
        self.position = torch.zeros(n, k, 2)
        """Agent positions, [num_envs, K, 2]."""
        self.goal = torch.zeros(n, k, 2)
        """Goal positions, [num_envs, K, 2]."""
        self.steps = torch.zeros(n, 1, dtype=torch.long)
        """Steps taken in the current episode, [num_envs, 1]."""
        self.generator = torch.Generator()

    def _observation(self) -> TensorDict:
        observation = torch.cat([self.position, self.goal - self.position], -1)
        agents = TensorDict({"observation": observation}, observation.shape[:-1])
        return TensorDict({GROUP: agents}, self.batch_size)

    def _reset(self, tensordict: TensorDictBase | None) -> TensorDictBase:
        reset = None if tensordict is None else tensordict.get("_reset", None)
        reset = torch.ones_like(self.steps, dtype=torch.bool) if reset is None else reset
        for state in (self.position, self.goal):
            fresh = torch.rand(state.shape, generator=self.generator) * 2 - 1
            state.copy_(torch.where(reset.unsqueeze(-1), fresh, state))
        self.steps.masked_fill_(reset, 0)
        return self._observation().update(self.full_done_spec.zero())

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        velocity = tensordict.get(ACTION).clamp(-1.0, 1.0)
        self.position.add_(self.step_size * velocity).clamp_(-1.0, 1.0)
        self.steps += 1
        distance = (self.goal - self.position).norm(dim=-1)
        team_reward = -distance.mean(-1, keepdim=True)
        truncated = self.steps >= self.episode_steps
        out = self._observation()
        out.set(REWARD, team_reward.unsqueeze(-2).expand_as(distance.unsqueeze(-1)).clone())
        out.update({"done": truncated, "terminated": torch.zeros_like(truncated)})
        return out.set("truncated", truncated)

    def _set_seed(self, seed: int | None) -> None:
        self.generator.manual_seed(seed)


def make_env(
    name: str,
    *,
    num_envs: int,
    episode_steps: int,
    seed: int,
    num_agents: int | None = None,
    device: str = "cpu",
) -> EnvBase:
    """``"team_navigation"`` (on the CPU) or ``"vmas:<scenario>"`` (needs ``pip install vmas``;
    on ``device``), with ``num_agents`` agents (the scenario's default if None)."""
    agents = (
        {}
        if num_agents is None
        else {"num_agents" if name == "team_navigation" else "n_agents": num_agents}
    )
    if name == "team_navigation":
        if torch.device(device).type != "cpu":
            raise ValueError(f"team_navigation runs on the CPU, got device {device!r}")
        env = TeamNavigationEnv(num_envs, episode_steps=episode_steps, **agents)
    elif name.startswith("vmas:"):
        from torchrl.envs.libs.vmas import VmasEnv

        env = VmasEnv(
            scenario=name.removeprefix("vmas:"),
            num_envs=num_envs,
            continuous_actions=True,
            max_steps=episode_steps,
            device=device,
            **agents,
        )
    else:
        raise ValueError(f"--env must be team_navigation or vmas:<scenario>, got {name!r}")
    env.set_seed(seed)
    return env


def make_actor(env: EnvBase, *, width: int, depth: int) -> ProbabilisticActor:
    """One MLP shared by every agent, reading its own observation: a tanh-Normal policy."""
    observation_dim = env.full_observation_spec[OBSERVATION].shape[-1]
    action_spec = env.full_action_spec_unbatched[ACTION]
    layers: list[nn.Module] = []
    for layer in range(depth):
        layers += [nn.Linear(observation_dim if layer == 0 else width, width), nn.Tanh()]
    network = nn.Sequential(
        *layers, nn.Linear(width, 2 * action_spec.shape[-1]), NormalParamExtractor()
    )
    return ProbabilisticActor(
        TensorDictModule(
            network, in_keys=[OBSERVATION], out_keys=[(GROUP, "loc"), (GROUP, "scale")]
        ),
        in_keys=[(GROUP, "loc"), (GROUP, "scale")],
        out_keys=[ACTION],
        distribution_class=TanhNormal,
        distribution_kwargs={"low": action_spec.space.low, "high": action_spec.space.high},
        return_log_prob=True,
    )


def centralised_mlp(env: EnvBase, *, width: int, depth: int) -> MultiAgentMLP:
    """MAPPO's critic network: one MLP on every agent's observation concatenated, a value per
    agent (the same for all of them)."""
    return MultiAgentMLP(
        n_agent_inputs=env.full_observation_spec[OBSERVATION].shape[-1],
        n_agent_outputs=1,
        n_agents=env.full_observation_spec[OBSERVATION].shape[-2],
        centralized=True,
        share_params=True,
        depth=depth,
        num_cells=width,
        activation_class=nn.Tanh,
    )


def make_mapoca_loss(
    env: EnvBase,
    actor: ProbabilisticActor,
    *,
    width: int,
    depth: int,
    value_network: str = "attention",
    baseline_network: str = "attention",
    **options,
) -> MAPOCALoss:
    """MAPOCALoss with the generic critics; its default keys are VMAS's.

    ``depth`` counts the critics' hidden layers as for MAPPO's MLP critic: each attention
    critic has an MLP before the attention and one after it, and they get ``depth // 2`` hidden
    layers each (at least one): critics as deep as MAPPO's, not twice as deep.
    ``value_network="mlp"`` takes MAPPO's critic network (``mlp_value``) as the value instead
    of ``CentralValue``; ``baseline_network="mlp"`` takes ``CounterfactualMLP``, as wide and
    deep as MAPPO's critic, instead of ``CounterfactualBaseline``.
    """
    observation_dim = env.full_observation_spec[OBSERVATION].shape[-1]
    num_agents = env.full_observation_spec[OBSERVATION].shape[-2]
    action_dim = env.full_action_spec[ACTION].shape[-1]
    half = max(1, depth // 2)
    if value_network == "mlp":
        value = mlp_value(num_agents, observation_dim, width=width, depth=depth)
    elif value_network == "attention":
        value = CentralValue(observation_dim, width=width, depth=half)
    else:
        raise ValueError(f"value_network must be 'attention' or 'mlp', got {value_network!r}")
    if baseline_network == "mlp":
        baseline = CounterfactualMLP(
            num_agents, observation_dim, action_dim, width=width, depth=depth
        )
    elif baseline_network == "attention":
        baseline = CounterfactualBaseline(observation_dim, action_dim, width=width, depth=half)
    else:
        raise ValueError(f"baseline_network must be 'attention' or 'mlp', got {baseline_network!r}")
    return MAPOCALoss(actor, value, baseline, **options)


def make_mappo_loss(
    env: EnvBase, actor: ProbabilisticActor, *, width: int, depth: int, **options
) -> MAPPOLoss:
    """torchrl's MAPPOLoss with its usual critic: one MLP on every agent's observation, a value
    per agent."""
    critic = TensorDictModule(
        centralised_mlp(env, width=width, depth=depth),
        in_keys=[OBSERVATION],
        out_keys=[(GROUP, "state_value")],
    )
    loss = MAPPOLoss(actor, critic, **options)
    loss.set_keys(value=(GROUP, "state_value"), reward=REWARD)
    return loss


LOSSES = {"MAPOCA": make_mapoca_loss, "MAPPO": make_mappo_loss}


def train(
    loss: LossModule,
    env: EnvBase,
    *,
    iterations: int,
    frames_per_batch: int,
    epochs: int,
    minibatch_size: int,
    lr: float,
    gamma: float,
    lmbda: float,
    max_grad_norm: float = 1.0,
    counterfactual_warmup: int = 0,
    deadline: float | None = None,
) -> list[float]:
    """Trains ``loss`` on ``env``; returns the mean team reward per step of every batch.

    With ``counterfactual_warmup`` n > 0 (MAPOCALoss only), the loss's ``counterfactual_weight``
    rises linearly from 0 at the first batch to 1 at batch n: the advantages start as G - V and
    end as MA-POCA's counterfactual G - b_i. With a ``deadline`` (a ``time.time()``), training
    stops after the first update that ends past it, the curve then shorter than ``iterations``.
    """
    loss.make_value_estimator(loss.default_value_estimator, gamma=gamma, lmbda=lmbda)
    optimiser = torch.optim.Adam(loss.parameters(), lr=lr)
    collector = Collector(
        env,
        loss.actor_network,
        frames_per_batch=frames_per_batch,
        total_frames=iterations * frames_per_batch,
        auto_register_policy_transforms=False,  # feed-forward policy: no recurrent state
    )
    mean_rewards = []
    for iteration, data in enumerate(collector):
        if counterfactual_warmup > 0:
            loss.counterfactual_weight = min(1.0, iteration / counterfactual_warmup)
        # torchrl's PPO and MAPPO examples make this call; MAPOCALoss accepts it as they do
        loss.value_estimator(
            data,
            params=loss.critic_network_params,
            target_params=loss.target_critic_network_params,
        )
        mean_rewards.append(data.get(("next", *REWARD)).mean().item())
        samples = data.reshape(-1)
        for _ in range(epochs):
            order = torch.randperm(samples.numel(), device=samples.device)
            for index in order.split(minibatch_size):
                losses = loss(samples[index])
                total = sum(value for key, value in losses.items() if key.startswith("loss_"))
                optimiser.zero_grad()
                total.backward()
                nn.utils.clip_grad_norm_(loss.parameters(), max_grad_norm)
                optimiser.step()
        collector.update_policy_weights_()
        if deadline is not None and time.time() > deadline:
            break
    collector.shutdown()
    return mean_rewards


def run(
    method: str,
    *,
    env_name: str,
    seed: int,
    args: argparse.Namespace,
    deadline: float | None = None,
) -> list[float]:
    """One training run of ``method`` ("MAPOCA" or "MAPPO") on a fresh environment, on
    ``args.device``; ``deadline`` as :func:`train`'s."""
    torch.manual_seed(seed)
    env = make_env(
        env_name,
        num_envs=args.num_envs,
        episode_steps=args.episode_steps,
        seed=seed,
        num_agents=args.agents,
        device=args.device,
    )
    actor = make_actor(env, width=args.width, depth=args.depth).to(args.device)
    critics = (
        {
            "value_network": args.value_network,
            "baseline_network": args.baseline_network,
            "least_variance_weight": args.least_variance_weight,
        }
        if method == "MAPOCA"
        else {}
    )
    loss = LOSSES[method](
        env,
        actor,
        width=args.critic_width or args.width,
        depth=args.critic_depth,
        **critics,
        clip_epsilon=0.2,
        entropy_coeff=args.entropy_coeff,
    ).to(args.device)
    return train(
        loss,
        env,
        iterations=args.iterations,
        frames_per_batch=args.num_envs * args.episode_steps,  # one episode per environment
        epochs=args.epochs,
        minibatch_size=args.minibatch_size,
        lr=args.lr,
        gamma=args.gamma,
        lmbda=args.lmbda,
        counterfactual_warmup=args.counterfactual_warmup if method == "MAPOCA" else 0,
        deadline=deadline,
    )


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--env", default="team_navigation")
    parser.add_argument("--methods", nargs="+", default=list(LOSSES), choices=list(LOSSES))
    parser.add_argument("--seeds", nargs="+", type=int, default=[0])
    parser.add_argument("--iterations", type=int, default=30)
    parser.add_argument(
        "--agents", type=int, default=None, help="agents in the team (the task's default: None)"
    )
    parser.add_argument(
        "--device", default="cpu", help="where VMAS and the networks run (team_navigation: cpu)"
    )
    parser.add_argument("--num-envs", type=int, default=32)
    parser.add_argument("--episode-steps", type=int, default=20)
    parser.add_argument("--epochs", type=int, default=4)
    parser.add_argument("--minibatch-size", type=int, default=160)
    parser.add_argument("--lr", type=float, default=3e-3)
    parser.add_argument("--gamma", type=float, default=0.9)
    parser.add_argument("--lmbda", type=float, default=0.9)
    parser.add_argument("--entropy-coeff", type=float, default=0.0)
    parser.add_argument("--width", type=int, default=64, help="hidden width of the actor")
    parser.add_argument(
        "--critic-width",
        type=int,
        default=None,
        help="hidden width of both methods' critics (default: --width)",
    )
    parser.add_argument("--depth", type=int, default=2, help="hidden layers of the actor")
    parser.add_argument(
        "--critic-depth",
        type=int,
        default=2,
        help="hidden layers of MAPPO's critic; MA-POCA's critics get half as many before and "
        "half after their attention",
    )
    parser.add_argument(
        "--value-network",
        choices=("attention", "mlp"),
        default="attention",
        help="MA-POCA's value: CentralValue, or MAPPO's critic network",
    )
    parser.add_argument(
        "--baseline-network",
        choices=("attention", "mlp"),
        default="attention",
        help="MA-POCA's baselines: CounterfactualBaseline, or CounterfactualMLP (as wide and "
        "deep as MAPPO's critic)",
    )
    parser.add_argument(
        "--counterfactual-warmup",
        type=int,
        default=0,
        help="iterations over which MA-POCA's advantages move from G - V to G - b_i "
        "(MAPOCALoss's counterfactual_weight from 0 to 1); 0: G - b_i throughout",
    )
    parser.add_argument(
        "--least-variance-weight",
        action="store_true",
        help="MAPOCALoss's least_variance_weight: each batch lowers the counterfactual weight "
        "to the blend of V and b_i whose advantages vary least",
    )
    parser.add_argument("--final-iterations", type=int, default=5)
    parser.add_argument("--json", default=None, help="where to write the curves and the table")
    return parser.parse_args(argv)


def main(argv: list[str] | None = None) -> None:
    args = parse_args(argv)
    curves: dict[str, dict[int, list[float]]] = {method: {} for method in args.methods}
    seconds: dict[str, float] = {}
    for method in args.methods:
        start = time.perf_counter()
        for seed in args.seeds:
            curves[method][seed] = run(method, env_name=args.env, seed=seed, args=args)
        seconds[method] = time.perf_counter() - start
    print(f"{args.env}: mean team reward per step, last {args.final_iterations} iterations")
    print(f"{'method':8s} {'mean':>9s} {'sd':>7s} {'seeds':>5s} {'seconds':>8s}")
    table = {}
    for method, runs in curves.items():
        finals = [statistics.mean(curve[-args.final_iterations :]) for curve in runs.values()]
        sd = statistics.stdev(finals) if len(finals) > 1 else 0.0
        table[method] = {"mean": statistics.mean(finals), "sd": sd, "finals": finals}
        print(
            f"{method:8s} {table[method]['mean']:+9.3f} {sd:7.3f} {len(finals):5d} "
            f"{seconds[method]:8.1f}"
        )
    if args.json is not None:
        with open(args.json, "w") as file:
            json.dump({"args": vars(args), "table": table, "curves": curves}, file, indent=1)


if __name__ == "__main__":
    main()
