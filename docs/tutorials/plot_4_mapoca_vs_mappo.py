"""
MAPOCALoss beside MAPPO on a continuous-action task
===================================================

This tutorial trains :class:`~terrashift_rl.objectives.mapoca.MAPOCALoss` as a TorchRL user would
in a project of their own: a multi-agent environment with continuous actions, torchrl's
``Collector``, the training loop of torchrl's MAPPO example, and the generic critics
:class:`~terrashift_rl.modules.CentralValue` and
:class:`~terrashift_rl.modules.CounterfactualBaseline`, built from the sizes of the
observations and actions alone. torchrl's own ``MAPPOLoss`` trains beside it, with the same actor,
hyperparameters and loop, for comparison. It runs on the CPU in well under a minute.

The code is the script ``examples/mapoca_vs_mappo.py`` of the repository, which also runs the same
comparison over several seeds, or on a VMAS scenario (``pip install vmas``;
``python examples/mapoca_vs_mappo.py --env vmas:balance``).

The environment
---------------

``TeamNavigationEnv`` is a small pure-torch environment: K agents on a plane, each steering to a
goal of its own, and one reward for the whole team, minus the mean distance still to go. Every
agent's reward thus also carries the others' progress; MA-POCA's counterfactual baselines are
meant to take that noise out of each agent's advantage. Its keys are those of torchrl's VMAS
environments: the group ``"agents"`` (batch shape ``[*B, K]``), per-agent rewards and team done
flags, which are also :class:`MAPOCALoss`'s default keys.
"""

# %%
# The networks are small: on a CPU, one thread runs them faster than several competing ones.
import inspect
import sys
from pathlib import Path

import matplotlib.pyplot as plt
import torch

import terrashift_rl

torch.set_num_threads(1)
# examples/ sits beside the package in the repository
sys.path.insert(0, str(Path(terrashift_rl.__path__[0]).parent / "examples"))
import mapoca_vs_mappo as example  # noqa: E402

print(inspect.getsource(example.TeamNavigationEnv._step))
env = example.TeamNavigationEnv(32, num_agents=3, episode_steps=20)
print(env.full_observation_spec["agents"])
print(env.full_action_spec["agents"])

# %%
# The actor
# ---------
# One MLP shared by the agents reads each agent's own observation and parameterises a
# tanh-Normal distribution over its velocity, as in torchrl's MAPPO example. Both losses get
# this actor.
print(inspect.getsource(example.make_actor))

# %%
# MA-POCA's critics
# -----------------
# :class:`~terrashift_rl.modules.CentralValue` gives one value of the team's state,
# ``state_value`` ``[*B, 1]``: each agent's observation goes through an MLP, residual
# self-attention mixes the agents and a mean over them feeds an MLP.
# :class:`~terrashift_rl.modules.CounterfactualBaseline` gives one baseline per agent,
# ``("agents", "baseline")`` ``[*B, K, 1]``: agent i's attends over its own observation and the
# other agents' observation-action pairs, everything but agent i's action, as ML-Agents' POCA
# does. Neither fixes the number of agents. Both are TensorDict modules whose default keys are
# the loss's. ``depth`` is the number of hidden layers of each of their MLPs, the one before the
# attention and the one after it: ``depth=1`` gives them the two hidden layers of MAPPO's critic
# below.
from terrashift_rl.modules import CentralValue, CounterfactualBaseline  # noqa: E402

value = CentralValue(observation_dim=4, width=64, depth=1)
baseline = CounterfactualBaseline(observation_dim=4, action_dim=2, width=64, depth=1)
print(value.in_keys, "->", value.out_keys)
print(baseline.in_keys, "->", baseline.out_keys)
data = env.reset()
data["agents", "action"] = env.full_action_spec["agents", "action"].rand()
print(value(data)["state_value"].shape, baseline(data)["agents", "baseline"].shape)

# %%
# The two losses
# --------------
# ``MAPOCALoss`` takes the actor and the two critics. torchrl's ``MAPPOLoss`` takes the actor
# and its usual centralised critic, a ``MultiAgentMLP`` that reads every agent's observation and
# writes one value per agent. That per-agent value is what ``MAPOCALoss`` refuses, with a
# message saying what to do: its value is the team's, and the counterfactual baselines are its
# per-agent estimates.
print(inspect.getsource(example.make_mapoca_loss))
print(inspect.getsource(example.make_mappo_loss))

# %%
# Training
# --------
# One loop trains either loss, written as torchrl's MAPPO example writes it: a ``Collector``
# gathers one episode per environment; ``loss.value_estimator(data, params=...,
# target_params=...)`` computes the returns and advantages once per batch; then epochs of
# mini-batches. The loss to minimise is the sum of every ``loss_*`` term of the output. For
# MAPOCALoss that includes ``loss_baseline``, which a loop adding
# ``loss_objective + loss_critic + loss_entropy`` by name would leave out, leaving the baselines
# untrained: the loss warns once if a backward pass goes through ``loss_critic`` without it.
print(inspect.getsource(example.train))


def train(method: str, seed: int = 0) -> list[float]:
    torch.manual_seed(seed)
    env = example.make_env("team_navigation", num_envs=32, episode_steps=20, seed=seed)
    actor = example.make_actor(env, width=64, depth=2)
    loss = example.LOSSES[method](env, actor, width=64, depth=2, entropy_coeff=0.0)
    return example.train(
        loss,
        env,
        iterations=20,
        frames_per_batch=32 * 20,
        epochs=4,
        minibatch_size=160,
        lr=3e-3,
        gamma=0.9,
        lmbda=0.9,
    )


rewards = {method: train(method) for method in ("MAPOCA", "MAPPO")}
for method, curve in rewards.items():
    print(f"{method}: mean team reward per step {curve[0]:+.2f} -> {curve[-1]:+.2f}")

# %%
# The mean team reward per step rises from that of random actions (about -1) as the agents learn
# to head for their goals. One seed and a small budget make this a demonstration, not a
# benchmark; ``python examples/mapoca_vs_mappo.py --seeds 0 1 2 3 4 5`` compares the two over
# seeds, and ``--env vmas:<scenario>`` on VMAS. Besides the credit assignment, the comparison
# also sets the critics apart: attention over the agents for MA-POCA, an MLP on their
# concatenated observations for MAPPO. Early on, the counterfactual baselines fit the returns
# worse than the central value, and their error is noise in every agent's advantage:
# ``MAPOCALoss(..., counterfactual_weight=w)`` takes the advantages from G - (w b_i + (1 - w) V),
# and ``example.train(..., counterfactual_warmup=n)`` raises w from 0 to 1 over the first n
# iterations (``--counterfactual-warmup`` of the example), which put MA-POCA level with or above
# MAPPO on VMAS (docs/results.md, "MAPOCALoss on VMAS").
fig, ax = plt.subplots(figsize=(6, 3.5))
for method, curve in rewards.items():
    ax.plot(curve, label=method)
ax.set_xlabel("iteration (one episode per environment)")
ax.set_ylabel("mean team reward per step")
ax.legend()
plt.show()
