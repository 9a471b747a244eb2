"""
Getting started
===============

Install the package, create a batch of TerraShift environments, roll out random actions,
read the observation keys and render a frame. Everything here runs on the CPU in seconds.

Install
-------

.. code-block:: bash

    python3 -m venv .venv && . .venv/bin/activate
    pip install torch==2.13.0   # CPU-only machines: avoids the multi-GB CUDA build
    pip install -e .

Create an environment
---------------------

:class:`~terrashift_rl.envs.terrashift.TerraShiftEnv` steps a whole batch of environments at once.
Without a config it builds the paper's pretraining scene (15 x 15 ellipsoid columns, 8 wave
agents, 4 spheres); keyword arguments override any field of
:class:`~terrashift_rl.sim.config.TerraShiftConfig` (see :doc:`/environment`).
"""

import matplotlib.pyplot as plt
import torch

from terrashift_rl.envs import GROUP, TerraShiftEnv
from terrashift_rl.envs.render import render_frame

env = TerraShiftEnv(num_envs=4, device="cpu", seed=0)
print(env.config.grid_size, env.config.num_agents, env.config.num_objects)

# %%
# Observation keys
# ----------------
# The agents live in the TorchRL group ``"agents"`` (``GROUP``): per-agent entries have a
# batch shape ``[num_envs, num_agents]``. The scene (heightmap, spheres and goals) is shared
# by the team and sits at the root.

td = env.reset()
for key, value in td.items(include_nested=True, leaves_only=True):
    print(f"{str(key):40s} {tuple(value.shape)}  {value.dtype}")

# %%
# The specs say the same, with bounds: the actions of each agent are 6 numbers in [-1, 1]
# that change its wavelet's velocity, angular velocity, amplitude and widths.

print(env.full_action_spec[GROUP, "action"])

# %%
# Roll out random actions
# -----------------------
# :meth:`~torchrl.envs.EnvBase.rollout` without a policy samples uniform random actions. With
# ``break_when_any_done=False`` finished environments are reset in place, as collectors do.

rollout = env.rollout(32, break_when_any_done=False)
reward = rollout["next", GROUP, "reward"]
print("reward", tuple(reward.shape))  # [num_envs, steps, num_agents, 1]
print("mean team reward per decision:", reward[..., 0, 0].mean().item())

# %%
# Every agent receives the same team reward; the episode counters at the root count the
# goals reached and the spheres lost since each environment's last reset.

print("same reward for all agents:", bool((reward == reward[..., :1, :]).all()))
print("goals so far:", rollout["next", "episode_goals"][:, -1, 0].tolist())
print("out of bounds so far:", rollout["next", "episode_out_of_bounds"][:, -1, 0].tolist())

# %%
# Driving the environment by hand
# -------------------------------
# ``step_and_maybe_reset`` is what collectors call: it steps, then resets the environments
# that are done and returns the tensordict of the next decision.

generator = torch.Generator().manual_seed(0)
td = env.reset()
for _ in range(8):
    td[GROUP, "action"] = torch.rand(env.sim.action_shape, generator=generator) * 2 - 1
    out, td = env.step_and_maybe_reset(td)
print("last team reward:", out["next", GROUP, "reward"][:, 0, 0])

# %%
# Render a frame
# --------------
# :func:`~terrashift_rl.envs.render.render_frame` draws one environment headless with
# Matplotlib: the scene in perspective on the left (columns coloured by wave height, each
# sphere in the colour of its goal, goals translucent), the heightmap observation on the right.

frame = render_frame(env.sim, env_index=0, width=960, height=480)
fig, ax = plt.subplots(figsize=(9.6, 4.8))
ax.imshow(frame)
ax.set_axis_off()
plt.show()

# %%
# :func:`~terrashift_rl.envs.render.record_rollout` and
# :func:`~terrashift_rl.envs.render.save_video` turn a whole rollout into an MP4 or GIF; the
# evaluation recipe uses them (:doc:`/training`).
