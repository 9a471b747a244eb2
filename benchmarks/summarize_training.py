"""Prints a Markdown table of training runs from their logs and evaluation JSON.

    python benchmarks/summarize_training.py benchmarks/results/training/h100_run4[1-7]*.json

Each argument is a run summary (``compact_logs.py``'s JSON, which holds the run's evaluations)
or a ``scalars`` folder written by torchrl's CSVLogger (``logger=csv``; a recipe's own folder,
``<run dir>/logs/<run name>/scalars``, is labelled by its run folder and the overrides Hydra
recorded there, and the files ``<folder>_evaluation.json`` and
``<folder>_training_mode_evaluation.json`` beside it, ``recipes/evaluate.py``'s output, the
second with ``respawn=true``, add the evaluation columns). The columns: env-steps and
iterations logged, the median env-steps/s per iteration after the first, the means over the last
``--last`` iterations of the reward per decision and of goals and spheres lost per episode, the
take-off (the first iteration where the mean reward of the last ``--last`` crosses zero: its
env-steps and the minutes of iterations up to it), the iterations whose training success rate,
averaged the same way, is 0.9 or more (the highest such mean when none is), the entropy at the
first and last iteration, and per evaluated policy the success rate, goals and out-of-bounds
per episode and reward per decision. A summary keeps its last iterations one by one, so the
end-of-run means are exact; before them its curves are bin means, so take-off and the success
count are read at the bins' resolution there.
"""

from __future__ import annotations

import math
import statistics
from pathlib import Path

from common import (
    benchmark_parser,
    is_summary,
    read_evaluations,
    read_series,
    read_summary,
    run_label,
    table_header,
    table_row,
)

EVALUATIONS = ("evaluation", "training_mode_evaluation")


def rolling_means(values: list[float], window: int) -> list[float]:
    """Means of ``window`` consecutive values, one per value from the ``window``-th on."""
    return [statistics.mean(values[i - window : i]) for i in range(window, len(values) + 1)]


def take_off(steps: list[float], reward: list[float], speed: list[float], window: int) -> str:
    """Env-steps and minutes at the first iteration whose ``window``-iteration mean reward per
    decision is above zero; the minutes add up each iteration's env-steps over its env-steps/s."""
    for i, mean in enumerate(rolling_means(reward, window), start=window - 1):
        if mean > 0:
            seconds = sum(
                (step - previous) / rate
                for step, previous, rate in zip(steps[: i + 1], [0.0, *steps], speed, strict=False)
            )
            return f"{steps[i] / 1e6:.1f} M, {seconds / 60:.1f} min"
    return "none"


def successful_iterations(success: list[float], window: int) -> str:
    """Iterations whose ``window``-iteration mean success rate is 0.9 or more (windows with an
    iteration that resolved no sphere, whose success rate is NaN, do not count)."""
    means = [mean for mean in rolling_means(success, window) if not math.isnan(mean)]
    if not means:
        return ""
    count = sum(mean >= 0.9 for mean in means)
    return f"{count}" if count else f"none (at most {max(means):.2f})"


def row(folder: Path, last: int) -> list[str]:
    """The table cells of one run."""
    steps, reward = read_series(folder, "reward_per_decision")
    if not steps:
        raise SystemExit(f"{folder} has no reward_per_decision: not a training run's log")
    speed = read_series(folder, "env_steps_per_s")[1]
    entropy = read_series(folder, "entropy")[1]
    goals = read_series(folder, "goals_per_episode")[1][-last:]
    lost = read_series(folder, "out_of_bounds_per_episode")[1][-last:]
    cells = [
        run_label(folder),
        f"{steps[-1] / 1e6:.2f} M",
        f"{read_summary(folder)['iterations'] if is_summary(folder) else len(steps)}",
        f"{statistics.median(speed[1:]):,.0f}" if speed[1:] else "",
        f"{statistics.mean(reward[-last:]):+.4f}",
        f"{statistics.mean(goals):.2f}, {statistics.mean(lost):.2f}" if goals and lost else "",
        take_off(steps, reward, speed, last) if len(speed) == len(steps) else "",
        successful_iterations(read_series(folder, "success_rate")[1], last),
        f"{entropy[0]:.2f} → {entropy[-1]:.2f}" if entropy else "",
    ]
    evaluations = read_evaluations(folder)
    for suffix in EVALUATIONS:
        scores = evaluations.get(suffix, {})
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
    parser = benchmark_parser(__doc__)
    parser.add_argument("runs", nargs="+", type=Path, help="run summaries or scalars folders")
    parser.add_argument("--last", type=int, default=8, help="iterations averaged at the end")
    args = parser.parse_args()
    header = [
        "run",
        "env-steps",
        "iterations",
        "env-steps/s",
        f"reward / decision, last {args.last}",
        f"goals, out of bounds / episode, last {args.last}",
        "take-off",
        f"training success ≥ 0.9 ({args.last}-iteration mean), iterations",
        "entropy, first → last",
        "evaluation, sampled: success, goals, out of bounds, reward",
        "evaluation, Beta mean: same",
        "training mode, sampled: same",
        "training mode, Beta mean: same",
    ]
    print(table_header(header))
    for folder in args.runs:
        print(table_row(row(folder.resolve(), args.last)))


if __name__ == "__main__":
    main()
