"""Prints a Markdown table of training runs from their CSV logs and evaluation JSON.

    python benchmarks/summarize_training.py benchmarks/results/training/h200_x4_6.5min/*/

Each argument is a ``scalars`` folder written by torchrl's CSVLogger (``logger=csv``); a
recipe's own folder (``<run dir>/logs/<run name>/scalars``) is labelled by its run folder and
the overrides Hydra recorded there, any other folder by its name. A file
``<folder>_evaluation.json`` beside it (``recipes/evaluate.py``'s output) adds the evaluation
columns. The numbers are those of the tables in ``docs/results.md``: env-steps and iterations
logged, the median env-steps/s per iteration after the first, the means over the last
``--last`` iterations of the reward per decision and of goals and spheres lost per episode, the
entropy at the first and last iteration, and per evaluated policy the success rate, goals and
out-of-bounds per episode and reward per decision.
"""

from __future__ import annotations

import argparse
import json
import statistics
from pathlib import Path

from common import read_series, run_label


def row(folder: Path, last: int) -> list[str]:
    """The table cells of one run."""
    steps, reward = read_series(folder, "reward_per_decision")
    if not steps:
        raise SystemExit(f"{folder} has no reward_per_decision.csv: not a CSVLogger scalars folder")
    speed = read_series(folder, "env_steps_per_s")[1][1:]
    entropy = read_series(folder, "entropy")[1]
    goals = read_series(folder, "goals_per_episode")[1][-last:]
    lost = read_series(folder, "out_of_bounds_per_episode")[1][-last:]
    cells = [
        run_label(folder),
        f"{steps[-1] / 1e6:.2f} M",
        f"{len(steps)}",
        f"{statistics.median(speed):,.0f}" if speed else "",
        f"{statistics.mean(reward[-last:]):+.4f}",
        f"{statistics.mean(goals):.2f}, {statistics.mean(lost):.2f}" if goals and lost else "",
        f"{entropy[0]:.2f} → {entropy[-1]:.2f}" if entropy else "",
    ]
    evaluation = folder.with_name(f"{folder.name}_evaluation.json")
    scores = json.loads(evaluation.read_text()) if evaluation.is_file() else {}
    for policy in ("stochastic", "deterministic"):
        m = scores.get(policy)
        cells.append(
            ""
            if m is None
            else f"{m['success_rate']:.3f}, {m['goals_per_episode']:.2f}, "
            f"{m['out_of_bounds_per_episode']:.2f}, {m['mean_reward_per_decision']:+.4f} "
            f"({m['episodes']:.0f} episodes)"
        )
    return cells


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", nargs="+", type=Path, help="CSVLogger scalars folders")
    parser.add_argument("--last", type=int, default=8, help="iterations averaged at the end")
    args = parser.parse_args()
    header = [
        "run",
        "env-steps",
        "iterations",
        "env-steps/s",
        f"reward / decision, last {args.last}",
        f"goals, out of bounds / episode, last {args.last}",
        "entropy, first → last",
        "evaluation, sampled: success, goals, out of bounds, reward",
        "evaluation, Beta mean: same",
    ]
    print("| " + " | ".join(header) + " |")
    print("|" + "---|" * len(header))
    for folder in args.runs:
        print("| " + " | ".join(row(folder.resolve(), args.last)) + " |")


if __name__ == "__main__":
    main()
