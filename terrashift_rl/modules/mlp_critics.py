"""MA-POCA critics of MAPPO's kind, for a team of a fixed size and order.

- :class:`CounterfactualMLP` (its ``nn.Module``: :class:`MLPBaseline`): counterfactual
  baselines from one MLP on every agent's observation and every other agent's action, as
  MAPPO's critic is one MLP on every agent's observation; the keys and input checks of
  :class:`~terrashift_rl.modules.critics.CounterfactualBaseline`.
- :func:`mlp_value`: MAPPO's critic network as V, with
  :class:`~terrashift_rl.modules.critics.CentralValue`'s keys.

Cheaper than the attention critics of :mod:`terrashift_rl.modules.critics`, whose baselines
cost K^2 tokens per sample, at the price of a fixed number of agents.
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModule
from tensordict.utils import NestedKey
from torch import Tensor, nn
from torchrl.modules import MultiAgentMLP

from terrashift_rl.modules.critics import _Baseline

__all__ = ["CounterfactualMLP", "MLPBaseline", "mlp_value"]


class MLPBaseline(nn.Module):
    """Counterfactual baselines b_i of a team of ``num_agents``: an MLP on every agent's
    observation, every other agent's action and which agent i is.

    The first layer sees the observations and actions of all K agents concatenated, with agent
    i's action left out, and a learned vector of agent i's: it runs once on the whole team and
    takes away each agent's own action term, so that the K baselines cost one wide layer and K
    narrow ones, not K wide ones. Absent agents (mask False) contribute zeros.

    Args:
        num_agents: K.
        observation_dim: O, features per agent.
        action_dim: A, action dims per agent.

    Keyword Args:
        width: width of the hidden layers.
        depth: hidden layers (at least 1).
        activation_class: the hidden layers' activation.
    """

    def __init__(
        self,
        num_agents: int,
        observation_dim: int,
        action_dim: int,
        *,
        width: int = 128,
        depth: int = 2,
        activation_class: type[nn.Module] = nn.Tanh,
    ) -> None:
        super().__init__()
        if depth < 1:
            raise ValueError(f"MLPBaseline needs at least one hidden layer (depth), got {depth}.")
        self.num_agents, self.action_dim = num_agents, action_dim
        self.team = nn.Linear(num_agents * (observation_dim + action_dim), width)
        self.agent = nn.Parameter(torch.zeros(num_agents, width))
        layers: list[nn.Module] = [activation_class()]
        for _ in range(depth - 1):
            layers += [nn.Linear(width, width), activation_class()]
        layers.append(nn.Linear(width, 1))
        self.head = nn.Sequential(*layers)

    def forward(self, features: Tensor, action: Tensor, agent_mask: Tensor | None = None) -> Tensor:
        """[*B, K, O] observations and [*B, K, A] actions -> baselines [*B, K, 1]."""
        if agent_mask is not None:
            present = agent_mask.unsqueeze(-1).to(features.dtype)
            features, action = features * present, action * present
        team = self.team(torch.cat([features.flatten(-2), action.flatten(-2)], -1))
        # each agent's own action term of the first layer: [H, K * A] -> [K, A, H]
        action_weight = self.team.weight[:, -self.num_agents * self.action_dim :]
        action_weight = action_weight.t().reshape(self.num_agents, self.action_dim, -1)
        own = torch.einsum("...ka,kah->...kh", action, action_weight)  # K products, not B * K
        return self.head(team.unsqueeze(-2) - own + self.agent)


class CounterfactualMLP(_Baseline):
    """Counterfactual baselines b_i for a team of a fixed size, as a TensorDict module: the
    same keys as :class:`CounterfactualBaseline`, an :class:`MLPBaseline` inside.

    Cheaper than the attention baseline, whose cost grows as K^2 per sample: one MLP as wide
    as MAPPO's critic, with a narrow layer per agent. It needs every input to hold exactly
    ``num_agents`` agents, in a fixed order.

    Args:
        num_agents: K.
        observation_dim: O, features per agent.
        action_dim: A, action dims per agent (classes for integer actions).

    Keyword Args:
        width: width of the hidden layers.
        depth: hidden layers.
        activation_class: the hidden layers' activation.
        group: the agents' group.
        observation_key: defaults to ``(group, "observation")``.
        action_key: defaults to ``(group, "action")``.
        mask_key: defaults to ``(group, "mask")``.
        out_key: defaults to ``(group, "baseline")``.

    Examples:
        >>> from tensordict import TensorDict
        >>> baseline = CounterfactualMLP(3, 5, 2, width=16)
        >>> data = TensorDict({
        ...     ("agents", "observation"): torch.randn(4, 3, 5),
        ...     ("agents", "action"): torch.randn(4, 3, 2)}, [4])
        >>> baseline(data)["agents", "baseline"].shape
        torch.Size([4, 3, 1])
    """

    def __init__(
        self,
        num_agents: int,
        observation_dim: int,
        action_dim: int,
        *,
        width: int = 128,
        depth: int = 2,
        activation_class: type[nn.Module] = nn.Tanh,
        group: str = "agents",
        observation_key: NestedKey | None = None,
        action_key: NestedKey | None = None,
        mask_key: NestedKey | None = None,
        out_key: NestedKey | None = None,
    ) -> None:
        network = MLPBaseline(
            num_agents,
            observation_dim,
            action_dim,
            width=width,
            depth=depth,
            activation_class=activation_class,
        )
        super().__init__(
            network,
            observation_dim,
            action_dim,
            group=group,
            observation_key=observation_key,
            action_key=action_key,
            mask_key=mask_key,
            out_key=out_key,
        )
        self.num_agents = num_agents

    def forward(self, tensordict: TensorDictBase, **kwargs) -> TensorDictBase:
        observation_key = self.in_keys[0]
        observation = tensordict.get(observation_key, None)  # missing: named by the checks
        if (
            observation is not None
            and observation.ndim >= 2
            and (observation.shape[-2] != self.num_agents)
        ):
            raise ValueError(
                f"{type(self).__name__} was built for {self.num_agents} agents; "
                f"{observation_key!r} holds {observation.shape[-2]}."
            )
        return super().forward(tensordict, **kwargs)


class _FirstAgent(nn.Module):
    """The first agent's entry of [..., K, F]: the team value of a centralised critic."""

    def forward(self, values: Tensor) -> Tensor:
        return values[..., 0, :]


def mlp_value(
    num_agents: int,
    observation_dim: int,
    *,
    width: int = 128,
    depth: int = 2,
    activation_class: type[nn.Module] = nn.Tanh,
    group: str = "agents",
    observation_key: NestedKey | None = None,
    out_key: NestedKey = "state_value",
) -> TensorDictModule:
    """V(s) for a team of a fixed size: MAPPO's critic network (torchrl's centralised
    ``MultiAgentMLP``, one MLP on every agent's observation concatenated) as a TensorDict
    module with :class:`CentralValue`'s keys, writing [*B, 1].

    Examples:
        >>> from tensordict import TensorDict
        >>> value = mlp_value(3, 5, width=16)
        >>> data = TensorDict({("agents", "observation"): torch.randn(4, 3, 5)}, [4])
        >>> value(data)["state_value"].shape
        torch.Size([4, 1])
    """
    network = MultiAgentMLP(
        n_agent_inputs=observation_dim,
        n_agent_outputs=1,
        n_agents=num_agents,
        centralized=True,
        share_params=True,
        depth=depth,
        num_cells=width,
        activation_class=activation_class,
    )
    return TensorDictModule(
        nn.Sequential(network, _FirstAgent()),
        in_keys=[(group, "observation") if observation_key is None else observation_key],
        out_keys=[out_key],
    )
