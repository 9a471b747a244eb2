"""How far an untrained policy's random actions move the spheres, for initial action means.

Each ``--means`` entry is a ``model.initial_action_mean`` (six values: v_x, v_y, omega,
amplitude, sigma_x, sigma_y; ``centred`` for the default, an empty one). Actions are drawn from
the Beta that the policy head starts from where the rest of its output layers reads zero
(:func:`~terrashift_rl.modules.policy.initial_concentrations`), independently per decision,
environment and agent, on the pretraining scene with the main job's shape actions (the
wavelets, or ``--actuator`` on ``--column-shape``); one evaluation-mode episode (no respawn) per
environment. Such actions are what the first iterations of training collect: where they move
no sphere, no goal is reached and none is lost, and the reward tells the policy nothing about
sorting. Prints a table and writes JSON.

    python benchmarks/initial_exploration.py --num-envs 256 --means centred 0,0,0,-0.5,0,0
    python benchmarks/initial_exploration.py --actuator surface_flow --column-shape box
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import torch
from common import benchmark_parser, run_header, table_header, table_row, write_results
from tensordict import TensorDictBase

from terrashift_rl.envs import TerraShiftEnv
from terrashift_rl.modules.config import TerraShiftModelConfig
from terrashift_rl.modules.policy import initial_concentrations
from terrashift_rl.sim import ACTUATORS, COLUMN_SHAPES, TerraShiftConfig
from terrashift_rl.training.evaluation import evaluate, evaluation_scene


class InitialBetaPolicy:
    """Samples every action from the policy head's initial Beta on
    [-action_range, action_range] (torch's global generator: seed it first)."""

    def __init__(self, config: TerraShiftModelConfig, action_dim: int) -> None:
        self.alpha, self.beta = initial_concentrations(config, action_dim)
        self.action_range = config.action_range

    def __call__(self, td: TensorDictBase) -> TensorDictBase:
        shape = td.get(("agents", "observation")).shape[:-1] + self.alpha.shape
        alpha, beta = (c.to(td.device).expand(shape) for c in (self.alpha, self.beta))
        unit = torch.distributions.Beta(alpha, beta).sample()
        td.set(("agents", "action"), (unit * 2.0 - 1.0) * self.action_range)
        return td


def parse_mean(text: str) -> list[float]:
    """``centred`` or six comma-separated numbers."""
    return [] if text == "centred" else [float(value) for value in text.split(",")]


def main() -> None:
    parser = benchmark_parser(__doc__, device=True)
    parser.add_argument("--num-envs", type=int, default=256, help="episodes per mean")
    parser.add_argument("--seed", type=int, default=1, help="the scenes' and the actions' seed")
    parser.add_argument("--means", type=parse_mean, nargs="+", default=[[]])
    parser.add_argument("--actuator", default="wavelets", choices=ACTUATORS)
    parser.add_argument("--column-shape", default="ellipsoid", choices=COLUMN_SHAPES)
    parser.add_argument(
        "--out", type=Path, default=None, help="JSON path (default by family, columns, device)"
    )
    args = parser.parse_args()

    device = torch.device(args.device)
    name = f"initial_exploration_{args.actuator}_{args.column_shape}_{device.type}.json"
    out = args.out or Path(__file__).parent / "results" / name
    scene = evaluation_scene(
        TerraShiftConfig.preset(
            "pretrain", action_mode="shape", actuator=args.actuator, column_shape=args.column_shape
        )
    )
    payload = {
        "benchmark": "initial_exploration",
        **run_header(device),
        "scene": f"pretrain, {args.actuator} on {args.column_shape} columns, shape actions, "
        "evaluation mode (respawn off)",
        "episodes": args.num_envs,
        "seed": args.seed,
        "rows": [],
    }
    columns = [
        "initial action mean",
        "goal fraction",
        "lost / episode",
        "length",
        "reward / decision",
    ]
    policies = []
    for mean in args.means:  # every mean checked before the first is played
        try:
            model = dataclasses.replace(TerraShiftModelConfig(), initial_action_mean=mean)
            policies.append((mean, InitialBetaPolicy(model, action_dim=6)))
        except ValueError as error:
            parser.error(f"--means {','.join(map(str, mean)) or 'centred'}: {error}")
    print(table_header(columns))
    for mean, policy in policies:
        env = TerraShiftEnv(scene, num_envs=args.num_envs, device=device, seed=args.seed)
        torch.manual_seed(args.seed)
        scores = evaluate(env, policy, progress=False)
        row = {"initial_action_mean": mean, **scores}
        payload["rows"].append(row)
        write_results(out, payload)
        label = ", ".join(f"{value:g}" for value in mean) or "centred"
        print(
            table_row(
                [
                    label,
                    f"{scores['goal_fraction']:.3f}",
                    f"{scores['out_of_bounds_per_episode']:.2f}",
                    f"{scores['mean_episode_length']:.0f}",
                    f"{scores['mean_reward_per_decision']:+.4f}",
                ]
            )
        )
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
