"""Why MA-POCA starts slower than MAPPO on VMAS: variants of the example's MA-POCA run.

    python benchmarks/mapoca_slow_start.py --scenario balance --iterations 30 --seeds 0 1 2 \
        --runs attention:4 value-advantage:4 attention:2 mlp:2 \
        --output benchmarks/results/vmas_slow_start_balance.json

Every run is ``examples/mapoca_vs_mappo.py``'s ``run`` for MAPOCALoss (its actor, loop and
hyperparameters) with one thing changed. A run is named ``<variant>:<critic depth>``, the
critic depth as the example's ``--critic-depth`` counts it (hidden layers in all; the generic
critics put half before their attention and half after it):

- ``attention``: the example's MA-POCA, the generic critics ``CentralValue`` and
  ``CounterfactualBaseline``.
- ``value-advantage``: the same networks and losses, but the policy's advantages are G - V,
  the central value's, in place of the counterfactual G - b_i (MAPOCALoss's
  ``counterfactual_weight=0``); the baselines still train.
- ``mlp``: MLPs on concatenated inputs in place of attention (tanh, as MAPPO's critic): V on
  every agent's observation, b_i on agent i's observation and the other agents'
  observation-action pairs (in the order i+1, i+2, ... around the team), both ``depth`` hidden
  layers deep.

Per collected batch the output holds the mean reward per agent and step (the curve of
``vmas_parity.py``) and, from the value-estimation pass: the variance of the returns G
explained by V and by the baselines b_i, and the correlation of G - b_i with G - V over all
agents and steps.
"""

from __future__ import annotations

import argparse
import datetime
from pathlib import Path

import torch
from common import device_name, write_results
from tensordict.nn import TensorDictModule
from torch import nn
from vmas_parity import TRAINING_ARGS, _example

from terrashift_rl.objectives import MAPOCALoss
from terrashift_rl.objectives.mapoca import MAPOCAValueEstimator

example = _example()
VARIANTS = ("attention", "value-advantage", "mlp")


class RecordingEstimator:
    """The loss's value-estimation pass, then records how well V and b_i fit the returns."""

    def __init__(self, estimator: MAPOCAValueEstimator) -> None:
        self.estimator = estimator
        self.record: dict[str, list[float]] = {"ev_value": [], "ev_baseline": [], "corr": []}

    def __call__(self, data, **kwargs):
        data = self.estimator(data, **kwargs)
        returns, value = data["value_target"], data["state_value"]
        baseline = data["agents", "baseline"]
        counterfactual = returns.unsqueeze(-2) - baseline
        central = (returns - value).unsqueeze(-2).expand_as(counterfactual)
        pair = torch.stack([counterfactual.flatten(), central.flatten()])
        self.record["corr"].append(torch.corrcoef(pair)[0, 1].item())
        self.record["ev_value"].append((1 - (returns - value).var() / returns.var()).item())
        self.record["ev_baseline"].append((1 - counterfactual.var() / returns.var()).item())
        return data


class RecordingMAPOCALoss(MAPOCALoss):
    """MAPOCALoss whose value-estimation pass is a :class:`RecordingEstimator`."""

    def make_value_estimator(self, *args, **kwargs):
        super().make_value_estimator(*args, **kwargs)
        self._value_estimator = RecordingEstimator(self._value_estimator)
        return self


def _tanh_mlp(in_dim: int, width: int, depth: int) -> nn.Sequential:
    layers: list[nn.Module] = []
    for _ in range(depth):
        layers += [nn.Linear(in_dim, width), nn.Tanh()]
        in_dim = width
    return nn.Sequential(*layers, nn.Linear(width, 1))


class ConcatenatedValue(nn.Module):
    """V(s) from every agent's observation, concatenated: [*B, K, O] -> [*B, 1]."""

    def __init__(self, num_agents: int, observation_dim: int, width: int, depth: int) -> None:
        super().__init__()
        self.net = _tanh_mlp(num_agents * observation_dim, width, depth)

    def forward(self, observation: torch.Tensor) -> torch.Tensor:
        return self.net(observation.flatten(-2))


class ConcatenatedBaseline(nn.Module):
    """b_i from o_i and the others' (o_j, a_j), j = i+1, i+2, ... mod K: [*B, K, 1]."""

    def __init__(
        self, num_agents: int, observation_dim: int, action_dim: int, width: int, depth: int
    ) -> None:
        super().__init__()
        in_dim = observation_dim + (num_agents - 1) * (observation_dim + action_dim)
        self.net = _tanh_mlp(in_dim, width, depth)
        self.num_agents = num_agents

    def forward(self, observation: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        k = self.num_agents
        pairs = torch.cat([observation, action], -1)
        rows = [
            torch.cat(
                [observation[..., i, :], *(pairs[..., (i + j) % k, :] for j in range(1, k))], -1
            )
            for i in range(k)
        ]
        return self.net(torch.stack(rows, -2))


def make_loss(variant: str, made: list[MAPOCALoss]):
    """A loss factory of the example's signature for ``variant``; appends each loss to ``made``."""

    def factory(env, actor, *, width: int, depth: int, **options) -> MAPOCALoss:
        observation_dim = env.full_observation_spec[example.OBSERVATION].shape[-1]
        num_agents = env.full_observation_spec[example.OBSERVATION].shape[-2]
        action_dim = env.full_action_spec[example.ACTION].shape[-1]
        if variant == "mlp":
            value = TensorDictModule(
                ConcatenatedValue(num_agents, observation_dim, width, depth),
                in_keys=[example.OBSERVATION],
                out_keys=["state_value"],
            )
            baseline = TensorDictModule(
                ConcatenatedBaseline(num_agents, observation_dim, action_dim, width, depth),
                in_keys=[example.OBSERVATION, example.ACTION],
                out_keys=[("agents", "baseline")],
            )
        else:
            generic = example.make_mapoca_loss(env, actor, width=width, depth=depth)
            value, baseline = generic.value_network, generic.baseline_network
        if variant == "value-advantage":
            options["counterfactual_weight"] = 0.0  # G - V; the baselines still train
        made.append(RecordingMAPOCALoss(actor, value, baseline, **options))
        return made[-1]

    return factory


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenario", default="balance", help="a VMAS scenario")
    parser.add_argument("--runs", nargs="+", default=["attention:4", "value-advantage:4"])
    parser.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    parser.add_argument("--output", type=Path, default=None)
    args, example_argv = parser.parse_known_args(argv)
    torch.set_num_threads(1)
    results: dict[str, dict[int, dict[str, list[float]]]] = {}
    for run in args.runs:
        variant, critic_depth = run.split(":")
        if variant not in VARIANTS:
            raise SystemExit(f"unknown variant {variant!r}; one of {VARIANTS}")
        options = ["--num-envs", "60", "--episode-steps", "100", "--iterations", "30"]
        options += [*example_argv, "--env", f"vmas:{args.scenario}"]
        options += ["--critic-depth", critic_depth]
        example_args = example.parse_args(options)
        made: list[MAPOCALoss] = []
        example.LOSSES[run] = make_loss(variant, made)
        for seed in args.seeds:
            curve = example.run(run, env_name=example_args.env, seed=seed, args=example_args)
            records = made[-1].value_estimator.record
            records = {name: [round(v, 4) for v in values] for name, values in records.items()}
            results.setdefault(run, {})[seed] = {"reward": [round(v, 4) for v in curve], **records}
            print(run, seed, " ".join(f"{value:+.3f}" for value in curve), flush=True)
            if args.output is not None:
                write_results(
                    args.output,
                    {
                        "date": datetime.date.today().isoformat(),
                        "device": device_name(torch.device("cpu")),
                        "args": {key: getattr(example_args, key) for key in TRAINING_ARGS}
                        | {"runs": args.runs, "seeds": args.seeds},
                        "runs": results,
                    },
                )


if __name__ == "__main__":
    main()
