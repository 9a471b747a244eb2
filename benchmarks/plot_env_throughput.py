"""Plots env-steps/s against num_envs from env_throughput JSON files.

    python benchmarks/plot_env_throughput.py benchmarks/results/env_throughput_cuda.json \
        --out docs/figures/env_throughput_h100.png
"""

from __future__ import annotations

import json
from pathlib import Path

from common import benchmark_parser, save_palette_png
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure


def main() -> None:
    parser = benchmark_parser(__doc__)
    parser.add_argument("results", nargs="+", type=Path, help="env_throughput JSON files")
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    figure = Figure(figsize=(6.4, 4.0), dpi=110, layout="constrained")
    FigureCanvasAgg(figure)
    ax = figure.subplots()
    for path in args.results:
        result = json.loads(path.read_text())
        sizes = [row["num_envs"] for row in result["rows"]]
        for key, label in (("sim_steps_per_s", "simulator"), ("env_steps_per_s", "TorchRL env")):
            ax.plot(
                sizes,
                [row[key] for row in result["rows"]],
                marker="o",
                label=f"{label}, {result['device']}",
            )
    ax.set_xscale("log", base=2)
    ax.set_yscale("log")
    ax.set_xlabel("environments")
    ax.set_ylabel("env-steps/s (decisions)")
    ax.set_title(f"pretrain scene, {result['date']}")
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=8)
    save_palette_png(figure, args.out)


if __name__ == "__main__":
    main()
