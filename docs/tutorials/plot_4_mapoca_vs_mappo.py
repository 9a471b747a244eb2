"""
MAPOCALoss beside MAPPO on a VMAS task
======================================

This tutorial trains :class:`~terrashift_rl.objectives.mapoca.MAPOCALoss` as a TorchRL user would
in a project of their own: a VMAS scenario with continuous actions, torchrl's
``Collector``, the training loop of torchrl's MAPPO example, and the generic critics
:class:`~terrashift_rl.modules.CentralValue` and
:class:`~terrashift_rl.modules.CounterfactualBaseline`, built from the sizes of the
observations and actions alone. torchrl's own ``MAPPOLoss`` trains beside it, with the same actor,
hyperparameters and loop, for comparison. It runs on the CPU in about a minute.

The code is the script ``examples/mapoca_vs_mappo.py`` of the repository, which also runs the same
comparison over several seeds (``python examples/mapoca_vs_mappo.py --env vmas:navigation
--seeds 0 1 2``); VMAS comes with the ``vmas`` and ``docs`` extras (``pip install -e '.[vmas]'``).

The environment
---------------

VMAS's ``navigation`` scenario, through torchrl's ``VmasEnv``: 4 agents on a plane, each
steering to a goal of its own, avoiding the others; every agent gets the team's shaped reward
(the progress of all agents towards their goals) and a penalty for each collision. Every
agent's reward thus also carries the others' progress; MA-POCA's counterfactual baselines are
meant to take that noise out of each agent's advantage. torchrl's VMAS keys, the group
``"agents"`` (batch shape ``[*B, K]``), per-agent rewards and team done flags, are also
:class:`MAPOCALoss`'s default keys.
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

NUM_ENVS, EPISODE_STEPS = 32, 50
env = example.make_env("vmas:navigation", num_envs=NUM_ENVS, episode_steps=EPISODE_STEPS, seed=0)
print(env.full_observation_spec["agents"])
print(env.full_action_spec["agents"])
observation_dim = env.full_observation_spec["agents", "observation"].shape[-1]
action_dim = env.full_action_spec["agents", "action"].shape[-1]

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

value = CentralValue(observation_dim, width=64, depth=1)
baseline = CounterfactualBaseline(observation_dim, action_dim, width=64, depth=1)
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

# %%
# Early in training the counterfactual baselines fit the returns worse than the central value
# does, and their error is noise in every agent's advantage.
# ``MAPOCALoss(..., counterfactual_weight=w)`` takes the advantages from
# G - (w b_i + (1 - w) V): the central value's G - V at w = 0, MA-POCA's G - b_i at w = 1 (its
# default). ``train(..., counterfactual_warmup=n)`` raises w from 0 to 1 over the first n
# iterations, as the benchmark of docs/results.md ("MAPOCALoss on VMAS") does over 20 of 100.


def train(method: str, seed: int = 0) -> list[float]:
    torch.manual_seed(seed)
    env = example.make_env(
        "vmas:navigation", num_envs=NUM_ENVS, episode_steps=EPISODE_STEPS, seed=seed
    )
    actor = example.make_actor(env, width=64, depth=2)
    loss = example.LOSSES[method](env, actor, width=64, depth=2, entropy_coeff=0.0)
    return example.train(
        loss,
        env,
        iterations=15,
        frames_per_batch=NUM_ENVS * EPISODE_STEPS,  # one episode per environment
        epochs=4,
        minibatch_size=160,
        lr=3e-3,
        gamma=0.9,
        lmbda=0.9,
        counterfactual_warmup=5 if method == "MAPOCA" else 0,
    )


rewards = {method: train(method) for method in ("MAPOCA", "MAPPO")}
for method, curve in rewards.items():
    print(f"{method}: mean team reward per step {curve[0]:+.3f} -> {curve[-1]:+.3f}")

# %%
# The mean team reward per step rises from about zero, random motion's, as the agents learn to
# head for their goals. One seed and a small budget make this a demonstration, not a benchmark:
# ``python benchmarks/vmas_parity.py --scenarios navigation`` compares the two over six seeds of
# 100 iterations, final reward and area under the curve. Besides the credit assignment, the
# comparison also sets the critics apart: attention over the agents for MA-POCA, an MLP on their
# concatenated observations for MAPPO.
fig, ax = plt.subplots(figsize=(6, 3.5))
for method, curve in rewards.items():
    ax.plot(curve, label=method)
ax.set_xlabel("iteration (one episode per environment)")
ax.set_ylabel("mean team reward per step")
ax.legend()
plt.show()
