"""MAPOCALoss against torchrl's MAPPOLoss on cooperative VMAS scenarios: final reward and AUC.

    pip install -e ".[vmas]"
    python benchmarks/vmas_parity.py --scenario balance --seeds 0 1 2 3 4 5 --workers 2 \
        --output benchmarks/results/vmas_parity_balance.json
    python benchmarks/vmas_parity.py --table benchmarks/results/vmas_parity_*.json

Every run is ``examples/mapoca_vs_mappo.py``'s ``run`` (same actor, loop and hyperparameters
for both losses; MAPOCALoss with the generic critics, MAPPOLoss with its centralised
``MultiAgentMLP`` critic); the example's options pass through (``--iterations``,
``--num-envs``, ``--episode-steps``, ``--lr``, ...). The defaults here are the example's on
VMAS's batch of torchrl's MAPPO example scaled down to a CPU: 60 environments of 100 steps
(6,000 frames per iteration), 100 iterations.

The curve of a run is the mean reward per agent and step of every collected batch. Its
**final reward** is the mean of the last ``--final-iterations`` points, its **AUC** the mean of
all of them (the area under the curve divided by the number of iterations). The output holds
both per seed, their mean ± sd over seeds, the ratios MAPOCA / MAPPO of the means (scores
negated for a reward below zero are not ratios: the difference is given too), and every curve
rounded to 4 decimals, from which ``--table`` redraws the table of docs/results.md.
"""

from __future__ import annotations

import argparse
import datetime
import importlib.util
import json
import multiprocessing
import statistics
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import torch
from common import device_name, write_results

AUC = "mean of the curve over all iterations (area under the curve / iterations)"
EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "mapoca_vs_mappo.py"
METHODS = ("MAPOCA", "MAPPO")


def _example():
    spec = importlib.util.spec_from_file_location("mapoca_vs_mappo", EXAMPLE)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _run(method: str, seed: int, argv: list[str]) -> tuple[str, int, list[float], float]:
    """One run in a worker process (one thread: the networks are small)."""
    torch.set_num_threads(1)
    example = _example()
    args = example.parse_args(argv)
    start = time.perf_counter()
    curve = example.run(method, env_name=args.env, seed=seed, args=args)
    return method, seed, curve, time.perf_counter() - start


def scores(curve: list[float], final_iterations: int) -> dict[str, float]:
    """Final reward (mean of the last ``final_iterations`` points) and AUC (mean of all)."""
    return {
        "final": statistics.mean(curve[-final_iterations:]),
        "auc": statistics.mean(curve),
    }


def summarise(curves: dict[str, dict[int, list[float]]], final_iterations: int) -> dict:
    """Per method: per-seed scores and their mean and sd; MAPOCA / MAPPO of the means."""
    table: dict[str, dict] = {}
    for method, runs in curves.items():
        if not runs:
            continue
        per_seed = {seed: scores(curve, final_iterations) for seed, curve in runs.items()}
        row: dict = {"seeds": sorted(per_seed)}
        for measure in ("final", "auc"):
            values = [per_seed[seed][measure] for seed in sorted(per_seed)]
            row[measure] = {
                "mean": statistics.mean(values),
                "sd": statistics.stdev(values) if len(values) > 1 else 0.0,
                "per_seed": values,
            }
        table[method] = row
    if all(method in table for method in METHODS):
        table["MAPOCA_vs_MAPPO"] = {
            measure: {
                "ratio": table["MAPOCA"][measure]["mean"] / table["MAPPO"][measure]["mean"],
                "difference": table["MAPOCA"][measure]["mean"] - table["MAPPO"][measure]["mean"],
            }
            for measure in ("final", "auc")
        }
    return table


TRAINING_ARGS = (
    "env", "agents", "iterations", "num_envs", "episode_steps", "epochs", "minibatch_size", "lr",
    "gamma", "lmbda", "entropy_coeff", "width", "depth", "critic_depth", "counterfactual_warmup",
)  # fmt: skip
"""The example's options that shape a run: outputs merged together must agree on them."""
MAPOCA_ARGS = ("counterfactual_warmup",)
"""Those that shape MA-POCA's runs alone: outputs without MA-POCA runs need not agree on them."""


def merge(results: list[dict], final_iterations: int, seeds: list[int] | None = None) -> dict:
    """One output from several of the same settings (say, one per method, run side by side):
    the curves together (of ``seeds`` only, if given), the table recomputed, every source's
    command or settings kept."""
    # the example's options --agents, --critic-depth and --counterfactual-warmup were None, 2
    # and 0 (their defaults) where a file predates them
    settings = [
        {"agents": None, "critic_depth": 2, "counterfactual_warmup": 0, **result["args"]}
        for result in results
    ]
    merged_args = {}
    for key in TRAINING_ARGS:
        # an option of MA-POCA's alone need not agree with outputs that hold no MA-POCA run
        relevant = [
            setting
            for setting, result in zip(settings, results, strict=True)
            if key not in MAPOCA_ARGS or "MAPOCA" in result["curves"]
        ] or settings
        values = {json.dumps(setting[key]) for setting in relevant}
        if len(values) > 1:
            raise ValueError(f"the outputs differ in {key}: {sorted(values)}")
        merged_args[key] = relevant[0][key]
    curves: dict[str, dict[int, list[float]]] = {}
    for result in results:
        for method, runs in result["curves"].items():
            for seed, curve in runs.items():
                if seeds is not None and int(seed) not in seeds:
                    continue
                if int(seed) in curves.get(method, {}):
                    raise ValueError(f"{method} seed {seed} is in more than one output")
                curves.setdefault(method, {})[int(seed)] = [round(value, 4) for value in curve]
    return {
        "date": max(result.get("date", "") for result in results),
        "device": results[0].get("device"),
        "sources": [
            {
                "command": result.get("command"),
                "date": result.get("date"),
                "args": result["args"],
                "runs": {method: sorted(runs) for method, runs in result["curves"].items()},
            }
            for result in results
        ],
        "args": merged_args | {"final_iterations": final_iterations},
        "auc": AUC,
        "final": f"mean of the curve over the last {final_iterations} iterations",
        "table": summarise(curves, final_iterations),
        "curves": curves,
    }


def read_output(source: str) -> dict:
    """An output file, ``FILE`` or ``FILE:METHOD`` (then with that method's runs only)."""
    path, _, method = source.rpartition(":")
    if method not in METHODS:
        return json.loads(Path(source).read_text())
    result = json.loads(Path(path).read_text())
    if method not in result["curves"]:
        raise ValueError(f"{path} holds no {method} runs")
    result["curves"] = {method: result["curves"][method]}
    return result


def markdown(results: list[dict]) -> str:
    """The table of docs/results.md for one or more output files; a row that repeats one
    above it (the same MAPPO runs in two outputs) is given once."""
    lines = [
        "| scenario | method | seeds | final reward | AUC | final, MAPOCA / MAPPO | "
        "AUC, MAPOCA / MAPPO |",
        "|---|---|---|---|---|---|---|",
    ]
    for result in results:
        table = result["table"]
        scenario = result["args"]["env"].removeprefix("vmas:")
        if result["args"].get("agents") is not None:
            scenario = f"{scenario}, {result['args']['agents']} agents"
        warmup = result["args"].get("counterfactual_warmup", 0)
        for method in METHODS:
            if method not in table:
                continue
            row = table[method]
            label = f"{method}, warm-up {warmup}" if method == "MAPOCA" and warmup else method
            cells = [f"{row[m]['mean']:+.4f} ± {row[m]['sd']:.4f}" for m in ("final", "auc")]
            ratios = ["", ""]
            if method == "MAPOCA" and "MAPOCA_vs_MAPPO" in table:
                ratios = [f"{table['MAPOCA_vs_MAPPO'][m]['ratio']:.3f}" for m in ("final", "auc")]
            line = (
                f"| {scenario} | {label} | {len(row['seeds'])} | {cells[0]} | {cells[1]} | "
                f"{ratios[0]} | {ratios[1]} |"
            )
            if line not in lines:
                lines.append(line)
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenario", default="balance", help="a VMAS scenario")
    parser.add_argument("--methods", nargs="+", default=list(METHODS), choices=METHODS)
    parser.add_argument(
        "--seeds", nargs="+", type=int, default=[0, 1, 2, 3, 4, 5], help="also of --merge"
    )
    parser.add_argument("--workers", type=int, default=1, help="runs at a time")
    parser.add_argument("--final-iterations", type=int, default=10)
    parser.add_argument("--output", type=Path, default=None)
    parser.add_argument(
        "--table",
        nargs="+",
        type=Path,
        default=None,
        help="print the table of these output files and exit",
    )
    parser.add_argument(
        "--merge",
        nargs="+",
        default=None,
        help="merge these output files (or the example's --json files) into --output and exit; "
        "FILE:METHOD takes only that method's runs of FILE",
    )
    args, example_argv = parser.parse_known_args(argv)
    if args.table is not None:
        print(markdown([json.loads(path.read_text()) for path in args.table]))
        return
    if args.merge is not None:
        outputs = [read_output(source) for source in args.merge]
        result = merge(outputs, args.final_iterations, args.seeds)
        print(markdown([result]))
        if args.output is not None:
            write_results(args.output, result)
        return
    example_argv = [
        "--num-envs", "60", "--episode-steps", "100", "--iterations", "100",
        *example_argv, "--env", f"vmas:{args.scenario}",
    ]  # fmt: skip
    example_args = _example().parse_args(example_argv)
    curves: dict[str, dict[int, list[float]]] = {method: {} for method in args.methods}
    seconds: dict[str, list[float]] = {method: [] for method in args.methods}

    def result() -> dict:
        return {
            "date": datetime.date.today().isoformat(),
            "device": device_name(torch.device("cpu")),
            "command": "python benchmarks/vmas_parity.py "
            + " ".join(sys.argv[1:] if argv is None else argv),
            "args": {key: getattr(example_args, key) for key in TRAINING_ARGS}
            | {"final_iterations": args.final_iterations},
            "auc": AUC,
            "final": f"mean of the curve over the last {args.final_iterations} iterations",
            "seconds_per_run": {m: statistics.mean(s) for m, s in seconds.items() if s},
            "table": summarise(curves, args.final_iterations),
            "curves": {
                method: {seed: [round(value, 4) for value in curve] for seed, curve in runs.items()}
                for method, runs in curves.items()
            },
        }

    jobs = [(method, seed) for seed in args.seeds for method in args.methods]
    with ProcessPoolExecutor(args.workers, mp_context=multiprocessing.get_context("spawn")) as pool:
        futures = [pool.submit(_run, method, seed, example_argv) for method, seed in jobs]
        for future in futures:
            method, seed, curve, elapsed = future.result()
            curves[method][seed] = curve
            seconds[method].append(elapsed)
            print(f"{method} seed {seed}: final {curve[-1]:+.4f}, {elapsed:.0f} s", flush=True)
            if args.output is not None:  # after every run: one stopped part-way keeps its runs
                write_results(args.output, result())
    print(markdown([result()]))


if __name__ == "__main__":
    main()
