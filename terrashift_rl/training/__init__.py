"""Training utilities the recipes compose: the on-policy trainer and its algorithms (MA-POCA,
MAPPO, IPPO), schedules, checkpoints, data parallelism over torchrun's processes."""

from terrashift_rl.training.algorithms import ALGORITHMS, Algorithm
from terrashift_rl.training.checkpoint import load_checkpoint, save_checkpoint
from terrashift_rl.training.run import run_training
from terrashift_rl.training.schedules import LinearSchedule
from terrashift_rl.training.trainer import (
    MAPOCATrainer,
    OnPolicyTrainer,
    TrainConfig,
    action_medians,
    concentration_metrics,
    episode_metrics,
    iterate_until,
    make_training_env,
)

__all__ = [
    "ALGORITHMS",
    "Algorithm",
    "LinearSchedule",
    "MAPOCATrainer",
    "OnPolicyTrainer",
    "TrainConfig",
    "action_medians",
    "concentration_metrics",
    "episode_metrics",
    "iterate_until",
    "load_checkpoint",
    "make_training_env",
    "run_training",
    "save_checkpoint",
]
