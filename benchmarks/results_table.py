"""Prints the summary table of docs/results.md: each recipe's evaluation over its seeds.

    python benchmarks/results_table.py \
        "teacher held=benchmarks/results/training/h100_run46_10min.json,...run47_10min.json" \
        --baselines benchmarks/results/training/baselines_evaluation_seed1.json

Each argument is ``label=summary,summary,...`` (split at the last ``=``): the run summaries
(``compact_logs.py``) of one recipe's seeds; a run continued in parts is its parts' summaries
joined with ``+`` (``a.json+a_part1.json``), whose curves are read as one and whose last part
holds its evaluation files. A row gives the mean ± standard deviation over
them of the evaluation-mode metrics (``recipes/evaluate.py``'s ``evaluation`` file, or else the
last periodic evaluation the run logged, ``eval_*``), the policy's mean action first and its
samples in parentheses where evaluated (``eval_sampled_*``, logged with
``run.eval_sampled=true``), with the env-steps and the training reward per decision over the
last 8 iterations. ``--baselines`` adds the random, zero and heuristic rows of an
``evaluate_baselines`` file, or those of a ``recipes/evaluate.py`` report (its scene's), also
the one a run summary holds.
``--evaluation pretraining_scene_evaluation`` reads another of a run's evaluation files.
``--env-steps N`` compares runs of different lengths at one budget: each row then reads the
periodic evaluation logged at N env-steps, and the training reward over the last 8 points
logged up to N (none for a finetune's zero-shot score at 0).
"""

from __future__ import annotations

import json
import statistics
from pathlib import Path

from common import (
    EVALUATION_SUFFIXES,
    benchmark_parser,
    joined_series,
    read_evaluations,
    run_parts,
    table_header,
    table_row,
)

METRICS = (
    ("goal_fraction", "{:.3f}"),
    ("success_rate", "{:.3f}"),
    ("out_of_bounds_per_episode", "{:.2f}"),
    ("mean_episode_length", "{:.0f}"),
    ("mean_reward_per_decision", "{:+.3f}"),
)


def spread(values: list[float], form: str) -> str:
    if len(values) == 1:
        return form.format(values[0])
    deviation = form.replace("+", "").format(statistics.stdev(values))
    return f"{form.format(statistics.mean(values))} ± {deviation}"


def scores(
    run: str | Path, at: int | None = None, file: str = "evaluation"
) -> dict[str, dict[str, float]]:
    """Evaluation-mode metrics of a run per policy kind (``deterministic``, ``stochastic``):
    its evaluation ``file``'s, else its last periodic evaluation, or the one at ``at``
    env-steps (``eval_*``, and ``eval_sampled_*`` where the run scored its samples too)."""
    evaluation = read_evaluations(run_parts(run)[-1]).get(file)
    if evaluation is not None and at is None:
        return {kind: evaluation[kind] for kind in ("deterministic", "stochastic")}
    result = {}
    for kind, prefix in (("deterministic", "eval_"), ("stochastic", "eval_sampled_")):
        logged = {
            name: dict(zip(*joined_series(run, f"{prefix}{name}"), strict=True))
            for name, _ in METRICS
        }
        if not all(logged.values()):
            continue
        if at is None:
            result[kind] = {name: list(values.values())[-1] for name, values in logged.items()}
        elif at in logged["goal_fraction"]:
            result[kind] = {name: values[at] for name, values in logged.items()}
        else:
            raise SystemExit(
                f"{run} has no evaluation at {at} env-steps: {list(logged['goal_fraction'])}"
            )
    if "deterministic" not in result:
        raise SystemExit(f"{run} holds no evaluation-mode score")
    return result


def row(
    label: str, runs: list[str | Path], at: int | None = None, file: str = "evaluation"
) -> list[str]:
    per_run = [scores(run, at, file) for run in runs]
    rewards = [joined_series(run, "reward_per_decision") for run in runs]
    cells = [label, str(len(runs))]
    end = statistics.mean(steps[-1] for steps, _ in rewards) if at is None else at
    cells.append(f"{end / 1e6:.1f} M")
    for name, form in METRICS:
        cell = spread([s["deterministic"][name] for s in per_run], form)
        if all("stochastic" in s for s in per_run):
            cell += f" ({spread([s['stochastic'][name] for s in per_run], form)})"
        cells.append(cell)
    training = [
        [r for s, r in zip(*series, strict=True) if at is None or s <= at][-8:]
        for series in rewards
    ]
    # none before a finetune's first iteration: its zero-shot row (at=0) leaves the cell empty
    cells.append(spread([statistics.mean(t) for t in training], "{:+.3f}") if all(training) else "")
    return cells


def main() -> None:
    parser = benchmark_parser(__doc__)
    parser.add_argument(
        "recipes", nargs="+", help="label=summary,summary,... (a run's parts joined by +)"
    )
    parser.add_argument(
        "--baselines", type=Path, help="an evaluate_baselines, evaluate.py or run summary JSON"
    )
    parser.add_argument("--env-steps", type=int, help="score every run at this many env-steps")
    parser.add_argument(
        "--evaluation",
        choices=EVALUATION_SUFFIXES,
        default="evaluation",
        help="which evaluation file of each run to read",
    )
    args = parser.parse_args()
    header = ["recipe", "seeds", "env-steps", *(name for name, _ in METRICS)]
    header.append("training reward / decision, last 8")
    print(table_header(header))
    for recipe in args.recipes:
        label, _, paths = recipe.rpartition("=")  # labels may hold overrides
        runs = paths.split(",")
        print(table_row(row(label, runs, args.env_steps, args.evaluation)))
    if args.baselines:
        saved = json.loads(args.baselines.read_text())  # evaluate_baselines' or evaluate.py's
        if "evaluations" in saved:  # a run summary: its evaluate.py report's
            saved = saved["evaluations"]["evaluation"]
        results = saved["results"] if "results" in saved else saved["baselines"]
        for name, metrics in results.items():
            cells = [f"{name} (baseline)", "", ""]
            cells += [form.format(metrics[metric]) for metric, form in METRICS] + [""]
            print(table_row(cells))


if __name__ == "__main__":
    main()
