"""
MAPOCALoss in another TorchRL project
=====================================

:class:`~terrashift_rl.objectives.mapoca.MAPOCALoss` is a plain TorchRL ``LossModule``: it needs a
multi-agent environment whose agents sit in one *group* (batch shape ``[*B, K]``), an actor, a
centralised value network and a counterfactual baseline network. Nothing in it is specific to
TerraShift. This tutorial trains it on an environment this project did not write, torchrl's
``MultiAgentCountingEnv`` (a mock from ``torchrl.testing``), on the CPU in well under a minute.

The same code is the script ``examples/mapoca_other_env.py`` of the repository
(``python examples/mapoca_other_env.py --iterations 60``).

The environment
---------------

The mock keeps each agent under its own key, ``("agents", "agent_<i>", ...)``; torchrl's
``Stack`` transform gathers them into one group, ``"team"``, the layout ``MAPOCALoss`` reads.
Its reward is always zero, so a small transform sets the task: the whole team earns 1 when
agent 0 answers whether the first feature of its observation exceeds 0.5, whatever the others
do. Only one agent's action matters; the counterfactual baselines are what lets the loss credit
it, and not the others, for the team reward.
"""

# %%
# The code is the example script's: this page imports it and shows each piece.
import inspect
import sys
from pathlib import Path

import matplotlib.pyplot as plt

import terrashift_rl

# examples/ sits beside the package in the repository
sys.path.insert(0, str(Path(terrashift_rl.__path__[0]).parent / "examples"))
import mapoca_other_env as example  # noqa: E402

print(inspect.getsource(example.make_env))
env = example.make_env(num_agents=3, episode_steps=5)
print(env.full_observation_spec["team"])

# %%
# The networks and the loss
# -------------------------
# An actor, a centralised value network and a counterfactual baseline network, built on the
# environment's specs; ``set_keys`` points the loss at the group ``"team"`` and its reward.
print(inspect.getsource(example.make_loss))

# %%
# Training
# --------
# A torchrl ``Collector`` gathers batches; ``loss.value_estimator`` computes the team returns
# from V and the per-agent advantages G - b_i once per batch; then epochs of mini-batches.
print(inspect.getsource(example.train))
rewards = example.train(
    iterations=20,
    num_envs=4,
    num_agents=3,
    episode_steps=5,
    steps_per_env=50,
    epochs=4,
    minibatch_size=50,
    seed=0,
)

# %%
# The mean team reward per step rises from chance (0.5) as agent 0 learns its answer.
fig, ax = plt.subplots(figsize=(6, 3.5))
ax.plot(rewards)
ax.set_xlabel("iteration")
ax.set_ylabel("mean team reward per step")
plt.show()
