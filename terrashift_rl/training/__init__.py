"""Training utilities the recipes compose: the settings room, the on-policy trainer and its
algorithms (MA-POCA, MAPPO, IPPO), TerraShift's parts and hooks for it, schedules, a run's
budget, checkpoints, loggers, signals, sizing for the machine, data parallelism over torchrun's
processes."""

from terrashift_rl.training.algorithms import (
    ALGORITHMS,
    Algorithm,
    IPPOConfig,
    LossConfig,
    MAPOCAConfig,
    MAPPOConfig,
)
from terrashift_rl.training.budget import iterate_until
from terrashift_rl.training.checkpoint import load_checkpoint, save_checkpoint
from terrashift_rl.training.schedules import LinearSchedule
from terrashift_rl.training.settings import RecipeConfig, TrainConfig
from terrashift_rl.training.terrashift import (
    action_medians,
    concentration_metrics,
    episode_metrics,
    make_trainer,
    make_training_env,
)
from terrashift_rl.training.trainer import (
    OnPolicyTrainer,
    TrainerHook,
)

__all__ = [
    "ALGORITHMS",
    "Algorithm",
    "IPPOConfig",
    "LinearSchedule",
    "LossConfig",
    "MAPOCAConfig",
    "MAPPOConfig",
    "OnPolicyTrainer",
    "RecipeConfig",
    "TrainConfig",
    "TrainerHook",
    "action_medians",
    "concentration_metrics",
    "episode_metrics",
    "iterate_until",
    "load_checkpoint",
    "make_trainer",
    "make_training_env",
    "save_checkpoint",
]
