"""Writes one compact JSON summary per training run, from which the plotting and summary
scripts draw, so that raw logs can stay out of git.

    python benchmarks/compact_logs.py outputs/<date>/<time>/logs/mapoca_pretrain/scalars \
        --name h100_adaptive_seed0 --device "NVIDIA H100 80GB HBM3" --date 2026-11-25

Each argument is a torchrl CSVLogger ``scalars`` folder. The summary holds the run's name,
device and date, the command-line overrides and resolved config when the folder is a recipe's
own (``<run dir>/logs/<run name>/scalars``), the evaluation files beside the folder
(``<folder>_<suffix>.json``, ``recipes/evaluate.py``'s output), and its curves: the metrics
logged every iteration as means over bins of consecutive iterations (at most ``--points``
bins, each at its last iteration's env-steps; the last ``--tail`` iterations are kept one by
one, so the end-of-run means of ``summarize_training.py`` are exact), the others (periodic
evaluations) point by point. Values keep 4 significant digits. Of the per-iteration curves
only those the docs and the scripts draw on are kept (``DRAWN_METRICS``; the periodic ones
all): ``--metrics`` names others, ``--metrics all`` keeps every one.
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from pathlib import Path

from common import benchmark_parser, read_evaluations, read_series, run_label, significant
from omegaconf import OmegaConf

DRAWN_METRICS = (
    "reward_per_decision",
    "success_rate",
    "env_steps_per_s",
    "goals_per_episode",
    "out_of_bounds_per_episode",
    "entropy",
    "kl_approx",
    "lr_trunk_policy",
    "concentration_amplitude",
    "curriculum_stage",
    "run_seconds",
)


def bin_means(values: list[float], size: int, tail: int) -> list[float]:
    """Means of consecutive ``size``-value bins up to the last ``tail`` values, then those;
    a bin's mean skips NaN (an iteration in which no episode ended logs a NaN success rate)."""
    head = len(values) - tail
    bins = [
        [v for v in values[i : min(i + size, head)] if not math.isnan(v)]
        for i in range(0, head, size)
    ]
    return [sum(b) / len(b) if b else math.nan for b in bins] + values[head:]


def bin_steps(steps: list[float], size: int, tail: int) -> list[float]:
    head = len(steps) - tail
    return [steps[min(i + size, head) - 1] for i in range(0, head, size)] + steps[head:]


def summarize(
    folder: Path,
    *,
    name: str,
    points: int,
    tail: int,
    metrics: Sequence[str] | None = DRAWN_METRICS,
    **meta: str | None,
) -> dict:
    steps, _ = read_series(folder, "reward_per_decision")
    if not steps:
        raise SystemExit(f"{folder} has no reward_per_decision.csv: not a CSVLogger scalars folder")
    tail = min(tail, len(steps))
    size = max(1, math.ceil((len(steps) - tail) / points))
    summary = {"run": name, **{k: v for k, v in meta.items() if v is not None}}
    if folder.name == "scalars":
        run_dir = folder.resolve().parents[2]
        for key, file in (("overrides", ".hydra/overrides.yaml"), ("config", "config.yaml")):
            if (run_dir / file).is_file():
                summary[key] = OmegaConf.to_container(OmegaConf.load(run_dir / file))
    summary.update(
        iterations=len(steps),
        bin_iterations=size,
        steps=[int(s) for s in bin_steps(steps, size, tail)],
        series={},
        sparse={},
        evaluations=read_evaluations(folder),
    )
    for path in sorted(folder.glob("*.csv")):
        metric_steps, values = read_series(folder, path.stem)
        if metric_steps == steps:
            if metrics is None or path.stem in metrics:
                summary["series"][path.stem] = significant(bin_means(values, size, tail), 4)
        else:
            points = [[int(s), v] for s, v in zip(metric_steps, values, strict=True)]
            summary["sparse"][path.stem] = significant(points, 4)
    return summary


def write_summary(summary: dict, out_dir: Path) -> Path:
    """Writes ``summary`` as compact JSON to ``<out_dir>/<its run name>.json``."""
    out = out_dir / f"{summary['run']}.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(summary, separators=(",", ":")))
    return out


def main() -> None:
    parser = benchmark_parser(__doc__)
    parser.add_argument("runs", nargs="+", type=Path, help="CSVLogger scalars folders")
    parser.add_argument("--name", help="the summary's name (one run only); default: its label")
    parser.add_argument("--device")
    parser.add_argument("--date")
    parser.add_argument("--points", type=int, default=48, help="bins per curve at most")
    parser.add_argument("--tail", type=int, default=16, help="last iterations kept one by one")
    parser.add_argument(
        "--metrics",
        nargs="+",
        default=list(DRAWN_METRICS),
        help="per-iteration curves to keep ('all': every one; default: DRAWN_METRICS)",
    )
    parser.add_argument(
        "--out-dir", type=Path, default=Path(__file__).parent / "results" / "training"
    )
    args = parser.parse_args()
    if args.name and len(args.runs) > 1:
        parser.error("--name names a single run")
    for folder in args.runs:
        name = args.name or run_label(folder).replace(" ", "_")
        summary = summarize(
            folder,
            name=name,
            points=args.points,
            tail=args.tail,
            metrics=None if args.metrics == ["all"] else args.metrics,
            device=args.device,
            date=args.date,
        )
        out = write_summary(summary, args.out_dir)
        print(f"wrote {out} ({out.stat().st_size / 1e3:.0f} kB)")


if __name__ == "__main__":
    main()
