"""How far one update moves the policy, against the learning rate, for each policy distribution.

From the same initial weights and the same environments, the trainer runs a few iterations
(collect, then the configured epochs of mini-batch updates) at each learning rate of the trunk
and policy, for a Beta policy (``model.distribution=beta``, the paper's) and a Gaussian one
(``normal``). Each row gives the mean over the iterations of the approximate KL divergence per
update and of the clip fraction (the trainer's own ``kl_approx`` and ``clip_fraction``). A
policy whose KL barely follows its learning rate cannot be steered by a KL-adaptive rate.
Prints a table and writes JSON after every row.

    python benchmarks/kl_response.py --device cpu --num-envs 64 --iterations 3 \
        --output benchmarks/results/kl_response_cpu.json
"""

from __future__ import annotations

import argparse
import copy
import statistics
from dataclasses import asdict
from datetime import date
from pathlib import Path

import torch
from common import device_name, write_results
from omegaconf import OmegaConf

from terrashift_rl.modules import TerraShiftModelConfig, make_terrashift_networks
from terrashift_rl.sim import TerraShiftConfig
from terrashift_rl.training import OnPolicyTrainer, TrainConfig, make_training_env

MODELS = Path(__file__).parent.parent / "recipes" / "configs" / "model"


def model_config(name: str, distribution: str) -> TerraShiftModelConfig:
    """The sizes of the recipes' ``model=<name>`` with the given distribution."""
    sizes = OmegaConf.to_container(OmegaConf.load(MODELS / f"{name}.yaml"))
    sizes.pop("defaults", None)
    return TerraShiftModelConfig(**sizes, distribution=distribution)


def measure(
    config: TerraShiftModelConfig, lr: float, args: argparse.Namespace, weights: dict
) -> dict:
    torch.manual_seed(args.seed)
    device = torch.device(args.device)
    networks = make_terrashift_networks(config).to(device)
    networks.load_state_dict(weights)
    env = make_training_env(
        TerraShiftConfig(), networks, num_envs=args.num_envs, device=device, seed=args.seed
    )
    train = TrainConfig(num_envs=args.num_envs, lr_trunk_policy=lr)
    trainer = OnPolicyTrainer(env, networks, train)
    rows = [trainer.train_iteration() for _ in range(args.iterations)]
    return {
        "kl_approx": statistics.mean(row["kl_approx"] for row in rows),
        "clip_fraction": statistics.mean(row["clip_fraction"] for row in rows),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--model", default="medium", help="a recipes/configs/model/ name")
    parser.add_argument("--num-envs", type=int, default=64)
    parser.add_argument("--iterations", type=int, default=3)
    parser.add_argument("--lrs", type=float, nargs="+", default=[3e-4, 1e-3, 3e-3, 1e-2])
    parser.add_argument("--distributions", nargs="+", default=["beta", "normal"])
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--output", type=Path, default=Path("kl_response.json"))
    args = parser.parse_args()
    payload = {
        "device": device_name(torch.device(args.device)),
        "date": date.today().isoformat(),
        "settings": {**vars(args), "output": str(args.output)},
        "train_config": asdict(TrainConfig(num_envs=args.num_envs)),
        "rows": [],
    }
    print("| distribution | learning rate | KL per update | clip fraction |")
    print("|---|---|---|---|")
    for distribution in args.distributions:
        config = model_config(args.model, distribution)
        torch.manual_seed(args.seed)
        weights = copy.deepcopy(make_terrashift_networks(config).state_dict())
        for lr in args.lrs:
            row = {"distribution": distribution, "lr": lr, **measure(config, lr, args, weights)}
            payload["rows"].append(row)
            write_results(args.output, payload)
            print(
                f"| {distribution} | {lr:g} | {row['kl_approx']:.2e} | {row['clip_fraction']:.3f} |"
            )


if __name__ == "__main__":
    main()
