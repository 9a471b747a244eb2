"""MAPOCALoss against torchrl's MAPPOLoss on cooperative VMAS scenarios: final reward and AUC.

    pip install -e ".[vmas]"
    python benchmarks/vmas_parity.py --scenarios balance:8 navigation:8 reverse_transport:8 \
        wheel:8 --seeds 0 1 2 3 4 --minibatch-size 400 --jobs 40 --out-dir results/vmas
    python benchmarks/vmas_parity.py --table results/vmas/vmas_parity_*.json

Every run is ``examples/mapoca_vs_mappo.py``'s ``run`` (same actor, frames, loop and optimiser
steps for both losses; MAPOCALoss with the generic critics of the README, MAPPOLoss with its
centralised ``MultiAgentMLP`` critic); the example's options pass through (``--iterations``,
``--num-envs``, ``--episode-steps``, ``--lr``, ...). The defaults here are the example's on
VMAS's batch of torchrl's MAPPO example scaled down: 60 environments of 100 steps (6,000
frames per iteration), 100 iterations, and MA-POCA's documented warm-up of its advantages
(``--counterfactual-warmup 20``). A scenario is ``NAME`` or ``NAME:AGENTS``; its reward
sharing (:data:`REWARD_SHARING`) goes into the output.

All runs (scenarios x methods x seeds) go out at once, ``--jobs`` at a time, in processes of one
CPU thread each. With ``--deadline`` S, a run stops after the first iteration that ends S
seconds after the start; the runs of a scenario are then scored over the iterations all of them
reached (the same frames for both methods), so the whole grid ends in about S seconds: give
``--jobs`` at least the number of runs, or the later ones start late and stop early.

The curve of a run is the mean reward per agent and step of every collected batch. Its
**final reward** is the mean of the last ``--final-fraction`` of the iterations, its **AUC**
the mean of all of them (the area under the curve divided by the number of iterations). Each
scenario's output, ``vmas_parity_<scenario>[_<agents>agents].json``, holds both per seed, their
mean +- sd over seeds, MAPOCA - MAPPO of the means in reward and in seed spreads (the larger of
the two sds), and every curve rounded to 4 decimals, from which ``--table`` redraws the table
of docs/results.md; ``summary.json`` holds the tables of all of them.
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
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path

import torch
from common import device_name, write_results

AUC = "mean of the curve over all iterations (area under the curve / iterations)"
EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "mapoca_vs_mappo.py"
METHODS = ("MAPOCA", "MAPPO")
REWARD_SHARING = {
    "balance": "one team reward: the package's progress to its goal, a penalty when the package "
    "or the line touches the floor",
    "navigation": "shared: the sum of every agent's progress to its goal and a bonus when all "
    "are there; a collision penalty of each agent's own",
    "transport": "one team reward: the package's progress to its goal",
    "wheel": "one team reward: minus how far the line's angular speed is from the target",
    "sampling": "one team reward: the sum of what every agent samples",
    "reverse_transport": "one team reward: the package's progress to its goal",
}
"""How each scenario the script runs shares its reward among the agents (VMAS's defaults):
one team reward is where credit assignment matters most."""


def _example():
    spec = importlib.util.spec_from_file_location("mapoca_vs_mappo", EXAMPLE)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _run(
    method: str, seed: int, argv: list[str], deadline: float | None
) -> tuple[list[float], float]:
    """One run in a worker process (one thread: the networks are small)."""
    torch.set_num_threads(1)
    example = _example()
    args = example.parse_args(argv)
    start = time.perf_counter()
    curve = example.run(method, env_name=args.env, seed=seed, args=args, deadline=deadline)
    return curve, time.perf_counter() - start


def scenario(spec: str) -> tuple[str, int | None]:
    """``NAME`` or ``NAME:AGENTS`` as the scenario's name and team size (None: its default)."""
    name, _, agents = spec.partition(":")
    if name not in REWARD_SHARING:
        raise argparse.ArgumentTypeError(
            f"unknown scenario {name!r}: one of {', '.join(REWARD_SHARING)}"
        )
    if agents and not (agents.isdigit() and int(agents) > 1):
        raise argparse.ArgumentTypeError(f"agents must be an integer above 1, got {agents!r}")
    return name, int(agents) if agents else None


def output_name(name: str, agents: int | None) -> str:
    return f"vmas_parity_{name}" + ("" if agents is None else f"_{agents}agents") + ".json"


def scores(curve: list[float], final_iterations: int) -> dict[str, float]:
    """Final reward (mean of the last ``final_iterations`` points) and AUC (mean of all)."""
    return {
        "final": statistics.mean(curve[-final_iterations:]),
        "auc": statistics.mean(curve),
    }


def summarise(curves: dict[str, dict[int, list[float]]], final_fraction: float) -> dict:
    """Per method: per-seed scores and their mean and sd, over the iterations every curve
    reached; MAPOCA / MAPPO and MAPOCA - MAPPO of the means, the difference also in seed
    spreads (the larger of the two sds)."""
    lengths = [len(curve) for runs in curves.values() for curve in runs.values()]
    iterations = min(lengths)
    final_iterations = max(1, round(final_fraction * iterations))
    table: dict[str, dict] = {"iterations": iterations, "final_iterations": final_iterations}
    for method, runs in curves.items():
        if not runs:
            continue
        per_seed = {
            seed: scores(curve[:iterations], final_iterations) for seed, curve in runs.items()
        }
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
        comparison = {}
        for measure in ("final", "auc"):
            mapoca, mappo = table["MAPOCA"][measure], table["MAPPO"][measure]
            difference = mapoca["mean"] - mappo["mean"]
            spread = max(mapoca["sd"], mappo["sd"])
            comparison[measure] = {
                "ratio": mapoca["mean"] / mappo["mean"] if mappo["mean"] else None,
                "difference": difference,
                "in_spreads": difference / spread if spread > 0 else None,
            }
        table["MAPOCA_vs_MAPPO"] = comparison
    return table


TRAINING_ARGS = (
    "env", "agents", "iterations", "num_envs", "episode_steps", "epochs", "minibatch_size", "lr",
    "gamma", "lmbda", "entropy_coeff", "width", "depth", "critic_width", "critic_depth",
    "value_network", "baseline_network", "counterfactual_warmup", "least_variance_weight",
)  # fmt: skip
"""The example's options that shape a run: outputs merged together must agree on them."""
MAPOCA_ARGS = (
    "value_network", "baseline_network", "counterfactual_warmup", "least_variance_weight",
)  # fmt: skip
"""Those that shape MA-POCA's runs alone: outputs without MA-POCA runs need not agree on them."""


def _curves(result: dict, seeds: list[int] | None = None) -> dict[str, dict[int, list[float]]]:
    """An output's curves, seeds as integers (of ``seeds`` only, if given)."""
    return {
        method: {
            int(seed): curve for seed, curve in runs.items() if seeds is None or int(seed) in seeds
        }
        for method, runs in result["curves"].items()
    }


def merge(results: list[dict], final_fraction: float, seeds: list[int] | None = None) -> dict:
    """One output from several of the same settings (say, one per method, run side by side):
    the curves together (of ``seeds`` only, if given), the table recomputed, every source's
    command or settings kept."""
    # the example's options --agents, --critic-width, --critic-depth, --counterfactual-warmup and
    # --least-variance-weight were None, None, 2, 0 and False (their defaults) where a file
    # predates them; the critics' networks went unrecorded (None)
    earlier = {
        "agents": None, "critic_width": None, "critic_depth": 2, "value_network": None,
        "baseline_network": None, "counterfactual_warmup": 0, "least_variance_weight": False,
    }  # fmt: skip
    settings = [{**earlier, **result["args"]} for result in results]
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
        for method, runs in _curves(result, seeds).items():
            for seed, curve in runs.items():
                if seed in curves.get(method, {}):
                    raise ValueError(f"{method} seed {seed} is in more than one output")
                curves.setdefault(method, {})[seed] = [round(value, 4) for value in curve]
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
        "args": merged_args | {"final_fraction": final_fraction},
        "auc": AUC,
        "final": f"mean of the curve over its last {final_fraction:.0%} of iterations",
        "table": summarise(curves, final_fraction),
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


def markdown(results: list[dict], final_fraction: float) -> str:
    """The table of docs/results.md for one or more outputs, scored from their curves; a row
    that repeats one above it (the same MAPPO runs in two outputs) is given once."""
    lines = [
        "| scenario | method | seeds | iterations | final reward | AUC | "
        "final, MAPOCA − MAPPO | AUC, MAPOCA − MAPPO |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for result in results:
        table = summarise(_curves(result), final_fraction)
        label = result["args"]["env"].removeprefix("vmas:")
        if result["args"].get("agents") is not None:
            label = f"{label}, {result['args']['agents']} agents"
        warmup = result["args"].get("counterfactual_warmup", 0)
        for method in METHODS:
            if method not in table:
                continue
            row = table[method]
            name = f"{method}, warm-up {warmup}" if method == "MAPOCA" and warmup else method
            cells = [f"{row[m]['mean']:+.4f} ± {row[m]['sd']:.4f}" for m in ("final", "auc")]
            differences = ["", ""]
            if method == "MAPOCA" and "MAPOCA_vs_MAPPO" in table:
                differences = [_difference(table["MAPOCA_vs_MAPPO"][m]) for m in ("final", "auc")]
            line = (
                f"| {label} | {name} | {len(row['seeds'])} | {table['iterations']} | "
                f"{cells[0]} | {cells[1]} | {differences[0]} | {differences[1]} |"
            )
            if line not in lines:
                lines.append(line)
    return "\n".join(lines)


def _difference(comparison: dict) -> str:
    """MAPOCA - MAPPO, and in seed spreads where there is one."""
    spreads = comparison["in_spreads"]
    text = f"{comparison['difference']:+.4f}"
    return text if spreads is None else f"{text} ({spreads:+.1f} sd)"


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--scenarios",
        nargs="+",
        type=scenario,
        default=[("balance", None)],
        help=f"NAME or NAME:AGENTS, NAME one of {', '.join(REWARD_SHARING)}",
    )
    parser.add_argument("--methods", nargs="+", default=list(METHODS), choices=METHODS)
    parser.add_argument(
        "--seeds", nargs="+", type=int, default=[0, 1, 2, 3, 4, 5], help="also of --merge"
    )
    parser.add_argument("--device", default="cpu", help="where VMAS and the networks run")
    parser.add_argument("--jobs", type=int, default=None, help="runs at a time (default: all)")
    parser.add_argument(
        "--deadline",
        type=float,
        default=None,
        help="seconds after which every run stops at the end of its iteration",
    )
    parser.add_argument("--final-fraction", type=float, default=0.1)
    parser.add_argument("--out-dir", type=Path, default=None, help="where the outputs go")
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
    parser.add_argument("--output", type=Path, default=None, help="the file --merge writes")
    args, example_argv = parser.parse_known_args(argv)
    if not 0 < args.final_fraction <= 1:
        parser.error(f"--final-fraction must be in (0, 1], got {args.final_fraction}")
    if args.table is not None:
        results = [json.loads(path.read_text()) for path in args.table]
        print(markdown(results, args.final_fraction))
        return
    if args.merge is not None:
        outputs = [read_output(source) for source in args.merge]
        result = merge(outputs, args.final_fraction, args.seeds)
        print(markdown([result], args.final_fraction))
        if args.output is not None:
            write_results(args.output, result)
        return
    example_argv = [
        "--num-envs", "60", "--episode-steps", "100", "--iterations", "100",
        "--counterfactual-warmup", "20", *example_argv, "--device", args.device,
    ]  # fmt: skip
    argvs = {
        (name, agents): [
            *example_argv,
            "--env",
            f"vmas:{name}",
            *([] if agents is None else ["--agents", str(agents)]),
        ]
        for name, agents in args.scenarios
    }
    runs = [
        (spec, method, seed) for spec in argvs for seed in args.seeds for method in args.methods
    ]
    curves = {spec: {method: {} for method in args.methods} for spec in argvs}
    seconds = {spec: {method: [] for method in args.methods} for spec in argvs}
    command = "python benchmarks/vmas_parity.py " + " ".join(sys.argv[1:] if argv is None else argv)
    date, device = datetime.date.today().isoformat(), device_name(torch.device(args.device))
    parse = _example().parse_args
    settings = {
        spec: {key: getattr(parse(spec_argv), key) for key in TRAINING_ARGS}
        for spec, spec_argv in argvs.items()
    }
    failed: list[str] = []

    def result(spec: tuple[str, int | None]) -> dict:
        return {
            "date": date,
            "device": device,
            "command": command,
            "reward_sharing": REWARD_SHARING[spec[0]],
            "args": settings[spec]
            | {"final_fraction": args.final_fraction, "deadline": args.deadline},
            "auc": AUC,
            "final": f"mean of the curve over its last {args.final_fraction:.0%} of iterations",
            "seconds_per_run": {m: statistics.mean(s) for m, s in seconds[spec].items() if s},
            "table": summarise(curves[spec], args.final_fraction),
            "curves": {
                method: {seed: [round(value, 4) for value in curve] for seed, curve in r.items()}
                for method, r in curves[spec].items()
            },
        }

    def write(spec: tuple[str, int | None]) -> None:
        """The scenario's output and the summary of every scenario with a run so far."""
        if args.out_dir is None:
            return
        write_results(args.out_dir / output_name(*spec), result(spec))
        done = [spec for spec in argvs if any(curves[spec].values())]
        summary = {
            "date": date,
            "device": device,
            "command": command,
            "failed": failed,
            "scenarios": {
                output_name(*spec): {
                    key: value for key, value in result(spec).items() if key != "curves"
                }
                for spec in done
            },
        }
        write_results(args.out_dir / "summary.json", summary)

    deadline = None if args.deadline is None else time.time() + args.deadline
    context = multiprocessing.get_context("spawn")
    with ProcessPoolExecutor(args.jobs or len(runs), mp_context=context) as pool:
        futures = {
            pool.submit(_run, method, seed, argvs[spec], deadline): (spec, method, seed)
            for spec, method, seed in runs
        }
        for future in as_completed(futures):
            spec, method, seed = futures[future]
            try:
                curve, elapsed = future.result()
            except Exception as error:  # the other runs go on; the run is named as failed
                failed.append(f"{output_name(*spec)} {method} seed {seed}: {error!r}")
                print(f"FAILED {failed[-1]}", flush=True)
                continue
            curves[spec][method][seed] = curve
            seconds[spec][method].append(elapsed)
            print(
                f"{output_name(*spec)} {method} seed {seed}: {len(curve)} iterations, "
                f"last {curve[-1]:+.4f}, {elapsed:.0f} s",
                flush=True,
            )
            write(spec)  # after every run: a grid stopped part-way keeps its runs
    print(
        markdown(
            [result(spec) for spec in argvs if any(curves[spec].values())], args.final_fraction
        )
    )
    if failed:
        sys.exit(f"{len(failed)} runs failed:\n" + "\n".join(failed))


if __name__ == "__main__":
    main()
