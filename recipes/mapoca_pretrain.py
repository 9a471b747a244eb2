"""MA-POCA pretraining on batched TerraShift environments.

    python recipes/mapoca_pretrain.py                                  # the paper's scene
    python recipes/mapoca_pretrain.py train.num_envs=1024 run.minutes=10 logger=csv
    python recipes/mapoca_pretrain.py run.resume=<run dir>/checkpoints/last.pt
    torchrun --standalone --nproc_per_node=4 recipes/mapoca_pretrain.py   # 4 GPUs, data-parallel

Config: recipes/configs/mapoca_pretrain.yaml (groups env, model, train, loss, logger). Without a
CUDA device, run.device=auto sizes the run for the CPU (run.cpu_defaults) where the command line
leaves a setting alone; a run from a checkpoint (run.resume, run.pretrained) builds its model.
Outputs (checkpoints, logs, resolved config) go to Hydra's run directory.
The run itself, config -> setup -> train loop -> cleanup, is
:func:`terrashift_rl.training.run.run_training`.
"""

from __future__ import annotations

import sys
from pathlib import Path

import hydra
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig

from terrashift_rl.training.run import (
    hydra_overrides_of_other_ranks,
    register_config_schemas,
    run_training,
    size_for_the_machine,
)

register_config_schemas()


@hydra.main(version_base=None, config_path="configs", config_name="mapoca_pretrain")
def main(cfg: DictConfig) -> None:
    cfg = size_for_the_machine(
        cfg,
        device_key="run.device",
        defaults_key="run.cpu_defaults",
        model_from=("run.resume", "run.pretrained"),  # the network must be the one they hold
    )
    run_training(cfg, run_dir=Path(HydraConfig.get().runtime.output_dir))


if __name__ == "__main__":
    sys.argv.extend(hydra_overrides_of_other_ranks())  # under torchrun, rank 0 alone writes
    main()
