"""Batched TerraShift simulator in NVIDIA Warp kernels (no torch.nn, no TorchRL)."""

import warp as wp

# Kernel compile and device messages are noise in tests and recipes; warnings still show.
wp.config.log_level = wp.LOG_WARNING

# isort: split

from terrashift_rl.sim.config import COLUMN_SHAPES, TerraShiftConfig
from terrashift_rl.sim.scene import ScriptedScene
from terrashift_rl.sim.simulator import Simulator

__all__ = ["COLUMN_SHAPES", "ScriptedScene", "Simulator", "TerraShiftConfig"]
