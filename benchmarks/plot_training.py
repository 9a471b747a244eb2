"""Plots learning curves from the CSV logs of training runs (``logger=csv``).

    python benchmarks/plot_training.py benchmarks/results/training/h100_run1_8min \
        benchmarks/results/training/h100_run2_6min --out docs/figures/pretrain_h100.png

Each argument is a ``scalars`` folder written by torchrl's CSVLogger (one ``<metric>.csv`` of
``step,value`` rows per metric). Draws reward per decision, success rate and throughput against
env-steps, with an optional reference line in the reward panel.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from common import read_series
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

PANELS = (
    ("reward_per_decision", "mean team reward per decision"),
    ("success_rate", "success rate (goals / resolved)"),
    ("env_steps_per_s", "env-steps/s (collection + update)"),
)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", nargs="+", type=Path, help="CSVLogger scalars folders")
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument(
        "--reference",
        type=float,
        default=None,
        help="a reward per decision to draw as a dashed line",
    )
    parser.add_argument("--reference-label", default="reference")
    args = parser.parse_args()
    figure = Figure(figsize=(13, 3.6), layout="constrained")
    FigureCanvasAgg(figure)
    axes = figure.subplots(1, len(PANELS))
    for ax, (metric, title) in zip(axes, PANELS, strict=True):
        for run in args.runs:
            steps, values = read_series(run, metric)
            ax.plot(
                [s / 1e6 for s in steps],
                values,
                marker="." if len(steps) < 10 else None,
                label=run.name,
            )
        if metric == "reward_per_decision" and args.reference is not None:
            ax.axhline(args.reference, linestyle="--", color="grey", label=args.reference_label)
        ax.set_title(title)
        ax.set_xlabel("env-steps (millions)")
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(args.out, dpi=110)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
