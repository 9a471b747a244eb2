"""Plots learning curves of training runs from their summaries or CSV logs (``logger=csv``).

    python benchmarks/plot_training.py benchmarks/results/training/h100_run46_10min.json \
        benchmarks/results/training/h100_run47_10min.json --out docs/figures/teacher.png

Each argument is a run summary (``compact_logs.py``'s JSON), a ``scalars`` folder written by
torchrl's CSVLogger (one ``<metric>.csv`` of ``step,value`` rows per metric) or one seed of a
``time_to_goal.py`` result, ``<result>.json#<seed>`` (the file alone if it holds one seed: its
evaluations' goal fractions, against training seconds that leave the evaluations out). Draws
one panel per metric against env-steps (by default reward per decision, success rate and
throughput), with an optional reference line in one panel (``--reference-metric``, the reward
by default); ``<metric>@minutes`` draws a metric against the run's minutes instead (its
``run_seconds``, evaluations included). A summary is labelled by its name, a recipe's own folder
(``<run dir>/logs/<run name>/scalars``) by its run folder and the overrides Hydra recorded
there, any other folder by its name.

    python benchmarks/plot_training.py <runs> --out curves.png \
        --metrics reward_per_decision out_of_bounds_per_episode entropy kl_approx
    python benchmarks/plot_training.py <runs> --out curves.png \
        --metrics eval_goal_fraction eval_goal_fraction@minutes curriculum_stage

A run continued in parts (``run.resume``, ``train_seeds.py --resume``) is drawn as one line
when its parts' summaries are joined with ``+``: ``<name>_seed0.json+<name>_seed0_part1.json``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from common import benchmark_parser, joined_series, run_label, run_parts, save_palette_png
from matplotlib import colormaps
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from terrashift_rl.sim.types import ACTION_NAMES

TITLES = {
    "reward_per_decision": "mean team reward per decision",
    "success_rate": "success rate (goals / resolved)",
    "env_steps_per_s": "env-steps/s (collection + update)",
    "goals_per_episode": "goals per episode",
    "out_of_bounds_per_episode": "spheres lost per episode",
    "entropy": "policy entropy (per agent)",
    "kl_approx": "approximate KL per update",
    "clip_fraction": "clip fraction",
    "lr_trunk_policy": "learning rate, trunk and policy",
    "eval_goal_fraction": "goal fraction (evaluation mode)",
    "eval_success_rate": "success rate (evaluation mode)",
    "eval_out_of_bounds_per_episode": "spheres lost per episode (evaluation mode)",
    "eval_mean_episode_length": "episode length (evaluation mode)",
    "curriculum_stage": "curriculum stage",
    "curriculum_eval_goal_fraction": "goal fraction at the current stage",
    **{f"concentration_{name}": f"median Beta α + β, {name}" for name in ACTION_NAMES},
    **{f"action_median_{name}": f"median action, {name}" for name in ACTION_NAMES},
}
DEFAULT_METRICS = ("reward_per_decision", "success_rate", "env_steps_per_s")


def panel_curve(run: str | Path, panel: str) -> tuple[np.ndarray, list[float]]:
    """One run's curve in a panel: ``<metric>`` against env-steps (millions), or
    ``<metric>@minutes`` against the run's minutes, its ``run_seconds`` interpolated at the
    metric's env-steps; no values where the run lacks either series."""
    metric, _, against = panel.partition("@")
    steps, values = joined_series(run, metric)
    if not against:
        return np.array(steps) / 1e6, values
    clock_steps, seconds = joined_series(run, "run_seconds")
    if not clock_steps:
        return np.array([]), []
    return np.interp(steps, clock_steps, seconds) / 60, values


def main() -> None:
    parser = benchmark_parser(__doc__)
    parser.add_argument(
        "runs", nargs="+", help="run summaries or scalars folders; a run's parts joined by +"
    )
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument(
        "--reference",
        type=float,
        default=None,
        help="a value of --reference-metric to draw as a dashed line",
    )
    parser.add_argument("--reference-label", default="reference")
    parser.add_argument("--reference-metric", default="reward_per_decision")
    parser.add_argument(
        "--metrics",
        nargs="+",
        default=list(DEFAULT_METRICS),
        help="logged metrics to draw, one panel each (the names of the runs' CSV files)",
    )
    args = parser.parse_args()
    # a legend beside the panels (more than ten runs) needs a line per run
    height = 3.6 if len(args.runs) <= 10 else max(3.6, 0.25 * len(args.runs))
    figure = Figure(figsize=(4.4 * len(args.metrics), height), dpi=110, layout="constrained")
    FigureCanvasAgg(figure)
    axes = figure.subplots(1, len(args.metrics), squeeze=False)[0]
    # a colour per run, the same in every panel (past ten runs, tab20's twenty)
    colours = colormaps["tab20" if len(args.runs) > 10 else "tab10"].colors
    for ax, panel in zip(axes, args.metrics, strict=True):
        metric, _, against = panel.partition("@")
        if against not in ("", "minutes"):
            parser.error(f"--metrics {panel}: only @minutes may follow a metric")
        for index, run in enumerate(args.runs):
            x, values = panel_curve(run, panel)
            if not values:  # a run without the panel's series is left out of it
                continue
            ax.plot(
                x,
                values,
                color=colours[index % len(colours)],
                marker="." if len(values) < 10 else None,
                label=run_label(run_parts(run)[0]),
            )
        if not ax.lines:
            parser.error(f"no run has {metric}" + (" and run_seconds" if against else ""))
        if metric == args.reference_metric and args.reference is not None:
            ax.axhline(args.reference, linestyle="--", color="grey", label=args.reference_label)
        ax.set_title(TITLES.get(metric, metric))
        ax.set_xlabel("minutes of the run" if against else "env-steps (millions)")
        ax.grid(alpha=0.3)
    if len(args.runs) > 10:  # a long legend goes beside the panels, not over the first
        handles, labels = axes[0].get_legend_handles_labels()
        figure.legend(handles, labels, loc="outside right upper", fontsize=8)
    else:
        axes[0].legend(fontsize=8)
    save_palette_png(figure, args.out)


if __name__ == "__main__":
    main()
