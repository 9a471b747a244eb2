"""The baselines of every actuator family: random, zero and scripted heuristic, over seeds.

For each family and column shape, :func:`~terrashift_rl.training.evaluation.evaluate_baselines`
plays one evaluation-mode episode (no respawn) per environment for each policy and seed;
the table gives the goal fraction (mean +- sd over seeds), the mean episode length in
decisions (the latency: an episode ends once every sphere is resolved), the share of
resolved spheres that reached their goal and the positive work the surface did on the
spheres per goal [J] (``count_surface_work``). Prints a table and writes JSON (after every row).

    python benchmarks/actuator_baselines.py --device cpu --num-envs 16 --seeds 0 1 2
    python benchmarks/actuator_baselines.py --device cuda --num-envs 1024 --shapes box
"""

from __future__ import annotations

import math
import statistics
from pathlib import Path

import torch
from common import benchmark_parser, run_header, table_header, table_row, write_results

from terrashift_rl.sim import ACTUATORS, COLUMN_SHAPES, TerraShiftConfig
from terrashift_rl.training.evaluation import evaluate_baselines

METRICS = ("goal_fraction", "mean_episode_length", "success_rate", "surface_work_per_goal")
"""Per policy, mean and sd over the seeds; the work per goal is NaN for a seed without goals."""


def mean_and_sd(values: list[float]) -> tuple[float, float]:
    """Mean and sample standard deviation over the seeds (0 for one seed); NaN if any is."""
    if any(math.isnan(value) for value in values):
        return math.nan, math.nan
    return statistics.fmean(values), statistics.stdev(values) if len(values) > 1 else 0.0


def main() -> None:
    parser = benchmark_parser(__doc__, device=True)
    parser.add_argument("--num-envs", type=int, default=16, help="episodes per policy and seed")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--actuators", nargs="+", default=sorted(ACTUATORS), choices=ACTUATORS)
    parser.add_argument("--shapes", nargs="+", default=["ellipsoid", "box"], choices=COLUMN_SHAPES)
    parser.add_argument("--out", type=Path, default=None, help="JSON path (default by device)")
    args = parser.parse_args()

    device = torch.device(args.device)
    out = args.out or Path(__file__).parent / "results" / f"actuator_baselines_{device.type}.json"
    payload = {
        "benchmark": "actuator_baselines",
        **run_header(device),
        "scene": "pretrain, evaluation mode (respawn off, shaping off)",
        "episodes_per_seed": args.num_envs,
        "seeds": args.seeds,
        "rows": [],
    }
    print(f"Baselines per actuator family, {args.num_envs} episodes x seeds {args.seeds}")
    print(table_header(["actuator", "columns", "policy", "goal fraction", "length", "success",
                        "work per goal [J]"]))  # fmt: skip
    for actuator in args.actuators:
        for shape in args.shapes:
            config = TerraShiftConfig.preset(
                "pretrain", actuator=actuator, column_shape=shape, count_surface_work=True
            )
            per_seed = [
                evaluate_baselines(config, num_envs=args.num_envs, device=device, seed=seed)
                for seed in args.seeds
            ]
            for scores in per_seed:
                for metrics in scores.values():
                    goals = metrics["goals_per_episode"]
                    work = metrics["surface_work_per_episode"]
                    metrics["surface_work_per_goal"] = work / goals if goals else math.nan
            for policy in per_seed[0]:
                row = {"actuator": actuator, "column_shape": shape, "policy": policy}
                for metric in METRICS:
                    values = [scores[policy][metric] for scores in per_seed]
                    row[metric], row[f"{metric}_sd"] = mean_and_sd(values)
                payload["rows"].append(row)
                write_results(out, payload)
                print(
                    table_row(
                        [
                            actuator,
                            shape,
                            policy,
                            f"{row['goal_fraction']:.3f} ± {row['goal_fraction_sd']:.3f}",
                            f"{row['mean_episode_length']:.1f}",
                            f"{row['success_rate']:.3f}",
                            f"{row['surface_work_per_goal']:.3f}",
                        ]
                    )
                )
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
