"""Batched TerraShift simulator in NVIDIA Warp kernels (no torch.nn, no TorchRL)."""

import warp as wp

# Kernel compile and device messages are noise in tests and recipes; warnings still show.
wp.config.log_level = wp.LOG_WARNING

from terrashift_rl.sim.actuators import ACTUATORS, Actuator  # noqa: E402
from terrashift_rl.sim.config import COLUMN_SHAPES, REWARD_TERMS, TerraShiftConfig  # noqa: E402
from terrashift_rl.sim.scene import ScriptedScene  # noqa: E402
from terrashift_rl.sim.simulator import Simulator  # noqa: E402

__all__ = [
    "ACTUATORS",
    "COLUMN_SHAPES",
    "REWARD_TERMS",
    "Actuator",
    "ScriptedScene",
    "Simulator",
    "TerraShiftConfig",
]
