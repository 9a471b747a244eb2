"""Tensordict keys read and written by the TerraShift networks.

Shapes use B for the batch dims of the tensordict ([N] for one step of N environments, [N, T]
for N trajectories of T steps), K agents, M object slots, L GRU layers and d the embedding width.
"""

from __future__ import annotations

__all__ = [
    "ACTION",
    "ACTION_LOG_PROB",
    "AGENT_EMBEDDING",
    "AGENT_MASK",
    "AGENT_OBSERVATION",
    "BASELINE",
    "BETA_CONCENTRATION0",
    "BETA_CONCENTRATION1",
    "CAMERA",
    "HEIGHTMAP",
    "IS_INIT",
    "NEXT_RECURRENT_STATE",
    "NORMAL_LOC",
    "NORMAL_SCALE",
    "OBJECTS",
    "OBJECTS_MASK",
    "PRIVILEGED_OBJECTS",
    "PRIVILEGED_OBJECTS_MASK",
    "RECURRENT_STATE",
    "STATE_VALUE",
]

HEIGHTMAP = "heightmap"
"""float32 [B, C, H, W] in [-1, 1]; read by the trunk."""
CAMERA = "camera"
"""float32 [B, C, H, W] in [0, 1], the overhead image; read by the trunk when its config has
``camera_channels``."""
OBJECTS = "objects"
"""float32 [B, M, 9]; read by the trunk."""
OBJECTS_MASK = "objects_mask"
"""bool [B, M], True where the slot holds an active object; absent means all active."""
PRIVILEGED_OBJECTS = ("privileged", "objects")
"""float32 [B, M, 9]: the object sequence handed to the critics alone; read by the value and
baseline heads with ``critic_objects``, never by the trunk or the policy."""
PRIVILEGED_OBJECTS_MASK = ("privileged", "objects_mask")
"""bool [B, M], as ``OBJECTS_MASK`` for ``PRIVILEGED_OBJECTS``; absent means all active."""
AGENT_OBSERVATION = ("agents", "observation")
"""float32 [B, K, 9] wavelet features in [-1, 1]; read by the trunk."""
AGENT_MASK = ("agents", "mask")
"""bool [B, K], True where the agent is present; absent means all present."""
IS_INIT = "is_init"
"""bool [B, 1] from torchrl's InitTracker, True at the first step of an episode."""
RECURRENT_STATE = ("agents", "recurrent_state")
"""float32 [B, K, L, d]: GRU state before this step; absent means zeros (fresh episodes)."""
NEXT_RECURRENT_STATE = ("next", *RECURRENT_STATE)
"""float32 [B, K, L, d]: GRU state after this step; written by the trunk."""
AGENT_EMBEDDING = ("agents", "embedding")
"""float32 [B, K, d]: per-agent trunk output; written by the trunk, read by every head."""
BETA_CONCENTRATION1 = ("agents", "concentration1")
"""float32 [B, K, A]: Beta alpha of each action dimension; written by the policy head."""
BETA_CONCENTRATION0 = ("agents", "concentration0")
"""float32 [B, K, A]: Beta beta of each action dimension; written by the policy head."""
NORMAL_LOC = ("agents", "loc")
"""float32 [B, K, A]: Gaussian mean of each action dimension; written by the Gaussian head."""
NORMAL_SCALE = ("agents", "scale")
"""float32 [B, K, A]: Gaussian standard deviation of each action dimension (state-independent);
written by the Gaussian head."""
ACTION = ("agents", "action")
"""float32 [B, K, A] in [-1, 1]; written by the actor, read by the baseline."""
ACTION_LOG_PROB = ("agents", "action_log_prob")
"""float32 [B, K]: joint log-probability of each agent's action (summed over A dims)."""
STATE_VALUE = "state_value"
"""float32 [B, 1]: centralised value V(s), one per environment."""
BASELINE = ("agents", "baseline")
"""float32 [B, K, 1]: counterfactual baseline b_i(s, a_-i), one per agent."""
