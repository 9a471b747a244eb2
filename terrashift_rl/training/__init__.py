"""Training utilities the recipes compose: the MA-POCA trainer, schedules, checkpoints."""

from terrashift_rl.training.checkpoint import load_checkpoint, save_checkpoint
from terrashift_rl.training.schedules import LinearSchedule
from terrashift_rl.training.trainer import (
    MAPOCATrainer,
    TrainConfig,
    concentration_metrics,
    episode_metrics,
    iterate_until,
    make_training_env,
)

__all__ = [
    "LinearSchedule",
    "MAPOCATrainer",
    "TrainConfig",
    "concentration_metrics",
    "episode_metrics",
    "iterate_until",
    "load_checkpoint",
    "make_training_env",
    "save_checkpoint",
]
