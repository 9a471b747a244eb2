"""MA-POCA finetuning: a pretraining checkpoint's weights on a larger scene.

    python recipes/mapoca_finetune.py run.pretrained=<pretrain run>/checkpoints/last.pt
    python recipes/mapoca_finetune.py run.pretrained=last.pt run.minutes=5 train.num_envs=1024
    torchrun --standalone --nproc_per_node=4 recipes/mapoca_finetune.py run.pretrained=last.pt

The networks are size-agnostic: the same weights run 15x15 with 8 agents and 30x30 with 16. The
model settings are the checkpoint's (unless the command line sets them), also on a CPU, where
they replace run.cpu_defaults' model=small.
Config: recipes/configs/mapoca_finetune.yaml (the pretraining config with env=finetune, the
critics warmed up for 8 iterations first and a KL-adaptive learning rate). The run is the
pretraining recipe's (recipes/mapoca_pretrain.py), started from the pretrained weights with a
fresh optimiser and fresh schedules.
"""

from __future__ import annotations

import sys

import hydra
from mapoca_pretrain import launch  # the pretraining recipe, in this file's folder
from omegaconf import DictConfig

from terrashift_rl.training.launch import hydra_overrides_of_other_ranks, refusals_end_the_run


@hydra.main(version_base=None, config_path="configs", config_name="mapoca_finetune")
@refusals_end_the_run()
def main(cfg: DictConfig) -> None:
    if not cfg.run.pretrained and not cfg.run.resume:
        raise ValueError(
            "finetuning needs run.pretrained=<pretraining checkpoint> (or run.resume=<a "
            "finetuning checkpoint> to continue one)"
        )
    launch(cfg)


if __name__ == "__main__":
    sys.argv.extend(hydra_overrides_of_other_ranks())  # under torchrun, rank 0 alone writes
    main()
