"""Time to goal: how long the pretraining recipe takes to sort, seed by seed.

Runs the recipe (``python recipes/mapoca_pretrain.py``, its defaults or ``--config-name``'s,
plus ``--overrides``) once per seed for ``--minutes`` each, evaluating every ``--eval-every``
iterations (evaluation mode, ``run.eval_episodes`` episodes on the same scenes each time),
logging to CSV. Seeds run side by side, one per GPU (``CUDA_VISIBLE_DEVICES``; with
``--processes N``, each seed data-parallel on N GPUs under torchrun), as many at a time as the
host has GPUs for, else one after another.

Per seed, from the run's logs:

- for each threshold (``--thresholds``, 0.95 and 0.90): the training seconds and env-steps at the
  first evaluation whose goal fraction reaches it (null if none did). Training seconds are the
  recipe's ``run_seconds`` (wall clock in its loop: collection, updates, checkpoints)
  less the seconds of the evaluations before: evaluation is reported, not counted;
- ``evaluation_seconds``, all evaluations together;
- ``env_steps_per_s``: env-steps over training seconds, end to end; and the medians over the
  iterations of the collection, value-estimation and epoch seconds (``collection_seconds``,
  ``estimation_seconds``, ``epochs_seconds``), which with ``iteration_seconds`` give the split;
- ``final_goal_fraction``: the last evaluation's, and ``final_evaluation`` its success rate,
  spheres out of bounds per episode, episode length in decisions and reward per decision;
  ``curve``: every evaluation's env-steps, training seconds and goal fraction;
  ``launch_seconds``: the process's wall clock (the last part's);
- with a curriculum, ``start_scene_goal_fraction``: the last score of its first stage's scene
  at the target (``curriculum.retention_every``), null if none came; ``stage_goal_fraction``:
  the last score of a stage's scene before the target (``curriculum.eval_every``; for a run
  that never reached the target, of the stage it stopped in), null if none came;
  ``stage_starts``: the env-steps at which each stage after the first began.

With ``--resume`` every seed's run kept in ``--keep`` by an earlier call goes on from its last
checkpoint (``run.resume``, the same command otherwise) for ``--minutes`` more, in the same
folder. A run longer than one machine's hold (a job's time limit, a lent GPU) is so measured
in parts; the recipe's clock goes on from the checkpoint, so the times to goal add up every
part's training seconds (each part's compilation included, the seconds between parts not).

With ``--stop-at-goal`` a seed's run is stopped, as Ctrl-C stops it (checkpoint written), at its
first evaluation that reaches every threshold: the times to goal are the same, the GPU is free
sooner, and ``final_goal_fraction`` is that evaluation's. Ctrl-C (or SIGTERM) stops the running
seeds the same way and writes what every seed has logged so far (``interrupted`` in the JSON and
in the entries of the seeds it cut short; seeds not started are left out), then exits with
status 130. A seed still running ``--grace`` seconds after its ``--minutes`` (both counted from
its launch, so its start-up, imports and Warp kernels, comes out of the grace) is stopped so too
and kept, marked ``interrupted`` unless its run had logged its last line already (its loop
over, only its exit left).

The JSON holds ``device``, ``date``, ``command``, ``seeds`` (one entry per seed), ``resumed``
(whether this call went on with kept runs), the medians over
seeds ``env_steps_per_s`` and ``median_seconds_to_goal`` (to the first threshold; null unless
more than half the seeds reached it) and ``inductor_cache``, the compile cache's folder and the
files it held at the start (a compiled update found there loads in seconds, compiling it takes
about a minute: the seconds to goal differ by that much), and prints a table.

    python benchmarks/time_to_goal.py --seeds 7 8 9 10 --minutes 8
    python benchmarks/time_to_goal.py --seeds 7 --processes 4 --minutes 4   # 4 GPUs, one seed
    python benchmarks/time_to_goal.py --config-name mapoca_pixels --seeds 7 8 9 --minutes 17
    python benchmarks/time_to_goal.py --smoke --seeds 0 1 --thresholds 0  # CPU: a launch check
    python benchmarks/time_to_goal.py --seeds 8 --minutes 24 --keep runs --overrides env=large \
        curriculum=auto   # then, on the next machine, the same with --resume: 48 minutes in all
"""

from __future__ import annotations

import argparse
import math
import os
import re
import shlex
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch
from common import (
    benchmark_parser,
    inductor_cache,
    read_series,
    run_header,
    table_header,
    table_row,
    write_results,
)

ROOT = Path(__file__).resolve().parents[1]
RECIPE = ROOT / "recipes" / "mapoca_pretrain.py"
GOAL = "eval_goal_fraction"
FINAL = (
    "success_rate",
    "out_of_bounds_per_episode",
    "mean_episode_length",
    "mean_reward_per_decision",
)
"""The last evaluation's metrics that a seed's entry keeps beside its goal fraction."""
LAST_LINE = re.compile(r"[\d,]+ env-steps in \d+ iterations; checkpoint ")
"""The line a run logs once its loop (and final evaluation) is over, whatever ended it."""


def recipe_command(seed: int, args: argparse.Namespace, run_dir: Path) -> list[str]:
    """The command line that trains ``seed``."""
    launcher = [sys.executable]
    if args.processes > 1:
        launcher += ["-m", "torch.distributed.run", "--standalone"]
        launcher += [f"--nproc_per_node={args.processes}"]
    settings = [f"run.seed={seed}", f"run.minutes={args.minutes}", "logger=csv"]
    settings += [f"run.eval_every={args.eval_every}", "run.best_window=0"]
    if args.smoke:
        settings = ["--config-name", "smoke", *settings, "run.total_env_steps=1000000000"]
    elif args.config_name:
        settings = ["--config-name", args.config_name, *settings]
    if args.resume:
        settings.append(f"run.resume={run_dir / 'checkpoints' / 'last.pt'}")
    return [*launcher, str(RECIPE), *settings, *args.overrides, f"hydra.run.dir={run_dir}"]


def summarize(
    seed: int, scalars: Path, thresholds: list[float], launch_seconds: float, eval_every: int
) -> dict:
    """One seed's entry, from its CSV logs (evaluations every ``eval_every`` iterations)."""
    eval_steps, goal_fractions = read_series(scalars, GOAL)
    _, eval_seconds = read_series(scalars, "eval_seconds")
    steps, run_seconds = read_series(scalars, "run_seconds")
    _, rates = read_series(scalars, "env_steps_per_s")
    _, collection_rates = read_series(scalars, "collection_steps_per_s")
    _, update_seconds = read_series(scalars, "update_seconds")
    _, estimation_seconds = read_series(scalars, "estimation_seconds")
    if not steps or not eval_steps:
        raise SystemExit(f"{scalars} holds no iterations or no evaluations")
    if any(later <= earlier for earlier, later in zip(steps, steps[1:], strict=False)):
        raise SystemExit(
            f"{scalars} logs an iteration's env-steps twice: a part of the run went on past the "
            "checkpoint that the next part resumed from (killed without writing one), so its "
            "seconds cannot be added up"
        )
    # the evaluations after an iteration: in the loop every eval_every iterations, after its
    # iteration's run_seconds was taken (the seconds of those at earlier iterations are what
    # to subtract), and a run's final one, after its loop and off the clock that a resumed
    # part continues from its checkpoint
    seconds_at = dict(zip(steps, run_seconds, strict=True))
    frames = steps[0]  # the env-steps of one iteration, every rank's
    evaluations = list(zip(eval_steps, goal_fractions, eval_seconds, strict=False))
    scored = [e for e in evaluations if e[0] in seconds_at]
    in_loop = [e for e in scored if round(e[0] / frames) % eval_every == 0]

    def training_seconds(step: float) -> float:
        earlier = sum(seconds for at, _, seconds in in_loop if at < step)
        return seconds_at[step] - earlier

    to_goal = {}
    for threshold in thresholds:
        reached = next((e for e in scored if e[1] >= threshold), None)
        to_goal[f"{threshold:g}"] = {
            "seconds": None if reached is None else training_seconds(reached[0]),
            "env_steps": None if reached is None else int(reached[0]),
        }
    last = steps[-1]
    iteration_seconds = [frames / rate for rate in rates]
    entry = {
        "seed": seed,
        "to_goal": to_goal,
        # each evaluation: env-steps, training seconds, goal fraction (to a tenth of a second
        # and four decimals: 128 episodes resolve no finer)
        "curve": [
            [int(at), round(training_seconds(at), 1), round(goal, 4)] for at, goal, _ in scored
        ],
        "final_goal_fraction": goal_fractions[-1],
        "final_evaluation": {
            name: series[-1]
            for name in FINAL
            if (series := read_series(scalars, f"eval_{name}")[1])
        },
        "evaluations": len(evaluations),
        "evaluation_seconds": sum(eval_seconds),
        "env_steps": int(last),
        "training_seconds": training_seconds(last),
        "env_steps_per_s": last / training_seconds(last),
        "iteration_seconds": statistics.median(iteration_seconds),
        "collection_seconds": statistics.median(frames / rate for rate in collection_rates),
        "estimation_seconds": statistics.median(estimation_seconds),
        "epochs_seconds": statistics.median(
            update - estimation
            for update, estimation in zip(update_seconds, estimation_seconds, strict=True)
        ),
        "launch_seconds": launch_seconds,
    }
    stage_steps, stages = read_series(scalars, "curriculum_stage")
    if stages:  # a curriculum run
        _, kept = read_series(scalars, "curriculum_start_eval_goal_fraction")
        entry["start_scene_goal_fraction"] = kept[-1] if kept else None
        _, staged = read_series(scalars, "curriculum_eval_goal_fraction")
        entry["stage_goal_fraction"] = staged[-1] if staged else None
        entry["stage_starts"] = [
            int(at)
            for at, stage, before in zip(stage_steps[1:], stages[1:], stages, strict=False)
            if stage > before
        ]
    return entry


def run_seeds(args: argparse.Namespace, folder: Path) -> tuple[list[dict], bool]:
    """Trains every seed, ``slots`` at a time, each on its own GPUs; returns their entries and
    whether Ctrl-C cut the benchmark short (:func:`interrupt`)."""
    gpus = torch.cuda.device_count() if not args.smoke else 0
    # the GPUs this process sees, as CUDA_VISIBLE_DEVICES names them for the seeds' processes
    visible = os.environ.get("CUDA_VISIBLE_DEVICES", ",".join(map(str, range(gpus)))).split(",")
    slots = max(1, gpus // args.processes) if gpus else 1
    pending, running, done, stopped = list(args.seeds), {}, [], set()
    free = list(range(slots))
    try:
        while pending or running:
            while pending and free:
                seed, slot = pending.pop(0), free.pop(0)
                run_dir = folder / f"seed_{seed}"
                env = {"OMP_NUM_THREADS": "1", **os.environ}
                if gpus:
                    first = slot * args.processes
                    env["CUDA_VISIBLE_DEVICES"] = ",".join(visible[first : first + args.processes])
                log = (folder / f"seed_{seed}.log").open("a" if args.resume else "w")
                part_start = log.tell()  # a resumed seed's earlier parts are in its log
                process = subprocess.Popen(
                    recipe_command(seed, args, run_dir),
                    cwd=folder,
                    env=env,
                    stdout=log,
                    stderr=subprocess.STDOUT,
                    start_new_session=True,  # torchrun's ranks are stopped with it on a timeout
                )
                running[seed] = (process, slot, time.perf_counter(), log, run_dir, part_start)
            time.sleep(1.0)
            for seed, (process, slot, start, log, run_dir, part_start) in list(running.items()):
                elapsed = time.perf_counter() - start
                if args.stop_at_goal and seed not in stopped and reached(run_dir, args.thresholds):
                    ctrl_c(process, args.processes)
                    stopped.add(seed)
                if process.poll() is None and elapsed < 60 * args.minutes + args.grace:
                    continue
                overran = process.returncode is None
                cut_short = overran and not logged_last_line(Path(log.name), part_start)
                if overran:
                    stop(process, args.processes, signalled=seed in stopped)
                log.close()
                del running[seed]
                free.append(slot)
                tail = (folder / f"seed_{seed}.log").read_text()[-4000:]
                if process.returncode != 0 and not (
                    overran
                    or (
                        seed in stopped
                        and ended_by_ctrl_c(process.returncode, args.processes, tail)
                    )
                ):
                    raise SystemExit(f"seed {seed} failed (status {process.returncode}):\n{tail}")
                entry = logged_entry(seed, run_dir, args, elapsed, interrupted=cut_short)
                if entry is not None:
                    done.append(entry)
    except KeyboardInterrupt:
        done += interrupt(running, stopped, args)
        return sorted(done, key=lambda entry: entry["seed"]), True
    return sorted(done, key=lambda entry: entry["seed"]), False


def interrupt(running: dict, stopped: set[int], args: argparse.Namespace) -> list[dict]:
    """After Ctrl-C: stops every running seed as Ctrl-C stops a run (checkpoint written; killed
    if it has not ended within a minute; those ``stopped`` at their goal already are only
    waited for) and returns the entries of those that logged an evaluation, marked
    ``interrupted``."""
    for seed, (process, *_) in running.items():
        if seed not in stopped:
            ctrl_c(process, args.processes)
    entries = []
    for seed, (process, _, start, log, run_dir, _) in running.items():
        stop(process, args.processes, signalled=True)
        log.close()
        elapsed = time.perf_counter() - start
        entry = logged_entry(seed, run_dir, args, elapsed, interrupted=True)
        if entry is not None:
            entries.append(entry)
    return entries


def logged_entry(
    seed: int, run_dir: Path, args: argparse.Namespace, elapsed: float, *, interrupted: bool
) -> dict | None:
    """A seed's entry from what its run logged, printed as a row of the table; None (and a
    message) if it logged no evaluation."""
    scalars = next(run_dir.glob("logs/*/scalars"), None)
    if scalars is None or not read_series(scalars, GOAL)[0]:
        print(f"seed {seed}: no evaluation logged", flush=True)
        return None
    entry = summarize(seed, scalars, args.thresholds, elapsed, args.eval_every)
    if interrupted:
        entry["interrupted"] = True
    note = " (interrupted)" if interrupted else ""
    print(table_row(table_cells(entry, args.thresholds)) + note, flush=True)
    return entry


def stop(process: subprocess.Popen, processes: int, *, signalled: bool) -> None:
    """Stops a seed's run as Ctrl-C stops one (:func:`ctrl_c`, unless ``signalled`` already),
    killing it if it has not ended within a minute."""
    if not signalled:
        ctrl_c(process, processes)
    try:
        process.wait(timeout=60)
    except subprocess.TimeoutExpired:
        os.killpg(process.pid, 9)
        process.wait()


def ctrl_c(process: subprocess.Popen, processes: int) -> None:
    """Ctrl-C to a seed's run, once: a run signalled twice quits without its checkpoint. Under
    torchrun to torchrun alone, which passes it on to every rank."""
    if processes > 1:
        process.send_signal(signal.SIGINT)
    else:
        os.killpg(process.pid, signal.SIGINT)


def logged_last_line(log: Path, part_start: int) -> bool:
    """Whether a run's log holds, past ``part_start`` (bytes), the line that ends a run: a run
    past its deadline that has logged it was only slow to exit."""
    with log.open("rb") as file:
        file.seek(part_start)
        return LAST_LINE.search(file.read().decode(errors="replace")) is not None


def ended_by_ctrl_c(status: int, processes: int, log_tail: str) -> bool:
    """Whether a run that :func:`ctrl_c` stopped ended as Ctrl-C ends one: the recipe with status
    130, torchrun by raising the signal it passed on."""
    return status == 130 or (processes > 1 and "SignalException" in log_tail)


def reached(run_dir: Path, thresholds: list[float]) -> bool:
    """Whether a running seed's logs hold an evaluation at or above every threshold."""
    scalars = next(run_dir.glob("logs/*/scalars"), None)
    _, goal_fractions = read_series(scalars, GOAL) if scalars else ([], [])
    return any(goal >= max(thresholds) for goal in goal_fractions)


def table_cells(entry: dict, thresholds: list[float]) -> list[str]:
    """A seed's row of the printed table."""

    def cell(value, spec: str) -> str:
        return "-" if value is None else format(value, spec)

    goals = [
        f"{cell(entry['to_goal'][f'{t:g}']['seconds'], '.0f')} s, "
        f"{cell(entry['to_goal'][f'{t:g}']['env_steps'], ',')}"
        for t in thresholds
    ]
    split = (
        f"{entry['collection_seconds']:.2f} / {entry['estimation_seconds']:.2f} / "
        f"{entry['epochs_seconds']:.2f}"
    )
    last = entry["final_evaluation"]
    final = (
        f"{entry['final_goal_fraction']:.3f}, {last['out_of_bounds_per_episode']:.2f} lost, "
        f"{last['mean_episode_length']:.0f} decisions"
    )
    return [
        entry["seed"],
        *goals,
        final,
        f"{entry['env_steps_per_s']:,.0f}",
        split,
        f"{entry['evaluation_seconds']:.0f}",
    ]


def main() -> None:
    parser = benchmark_parser(__doc__)
    parser.add_argument("--seeds", type=int, nargs="+", default=[7, 8, 9, 10])
    parser.add_argument("--minutes", type=float, default=8.0, help="run.minutes of each seed")
    parser.add_argument("--eval-every", type=int, default=10, help="iterations")
    parser.add_argument("--thresholds", type=float, nargs="+", default=[0.95, 0.90])
    parser.add_argument("--processes", type=int, default=1, help="GPUs per seed (torchrun)")
    parser.add_argument("--smoke", action="store_true", help="the smoke config, on the CPU")
    parser.add_argument(
        "--config-name",
        default=None,
        help="the recipe's config, e.g. mapoca_pixels (default: its own)",
    )
    parser.add_argument(
        "--grace",
        type=float,
        default=300.0,
        help="seconds past --minutes, counted from the seed's launch (its start-up included), "
        "before a run is stopped",
    )
    parser.add_argument(
        "--overrides", nargs="+", default=[], metavar="KEY=VALUE", help="more recipe overrides"
    )
    parser.add_argument(
        "--stop-at-goal", action="store_true", help="stop a seed once it reaches every threshold"
    )
    parser.add_argument("--out", type=Path, default=None)
    parser.add_argument("--keep", type=Path, default=None, help="keep the runs' folders here")
    parser.add_argument(
        "--resume",
        action="store_true",
        help="go on with the runs kept in --keep from their last checkpoints",
    )
    args = parser.parse_args()
    if args.resume:
        if args.keep is None:
            parser.error("--resume goes on with the runs kept in --keep: name that folder")
        missing = [
            seed
            for seed in args.seeds
            if not (args.keep / f"seed_{seed}" / "checkpoints" / "last.pt").is_file()
        ]
        if missing:
            parser.error(
                f"--resume: no checkpoints/last.pt in {args.keep}/seed_<seed> for seed(s) "
                f"{', '.join(map(str, missing))}"
            )
    if args.minutes <= 0 or args.eval_every < 1 or args.processes < 1:
        parser.error("--minutes must be > 0, --eval-every and --processes >= 1")
    if args.smoke and args.config_name:
        parser.error("--smoke runs the smoke config: leave out --config-name")
    device = torch.device("cpu" if args.smoke else "cuda")
    if device.type == "cuda" and torch.cuda.device_count() < args.processes:
        parser.error(f"--processes {args.processes}, but this host has fewer CUDA devices")
    if args.out is None:
        name = "time_to_goal_smoke" if args.smoke else f"time_to_goal_{device.type}"
        args.out = Path(__file__).parent / "results" / f"{name}.json"
    header = run_header(device)
    if args.processes > 1:
        header["device"] = f"{args.processes} x {header['device']}"
    example = recipe_command(args.seeds[0], args, Path("<run dir>"))
    example = [
        "python",
        *(str(RECIPE.relative_to(ROOT)) if p == str(RECIPE) else p for p in example[1:]),
    ]
    print(f"time to goal: {header['device']}, {len(args.seeds)} seed(s) of {args.minutes:g} min")
    print(f"each: {shlex.join(example)}")
    cache = inductor_cache()
    print(f"Inductor's cache at the start: {cache['folder']}, {cache['files']:,} files")
    goals = [f"to {t:g}: s, env-steps" for t in args.thresholds]
    columns = [
        "seed",
        *goals,
        "final: goal fraction, lost, decisions",
        "env-steps/s",
        "collect / estimate / epochs s",
        "eval s",
    ]
    print(table_header(columns))
    # Ctrl-C, also to a benchmark started in the background (which begins with SIGINT
    # ignored), and a scheduler's SIGTERM stop the seeds as Ctrl-C does (run_seeds)
    for number in (signal.SIGINT, signal.SIGTERM):
        signal.signal(number, signal.default_int_handler)
    with tempfile.TemporaryDirectory() as scratch:
        folder = args.keep or Path(scratch)
        folder.mkdir(parents=True, exist_ok=True)
        seeds, interrupted = run_seeds(args, folder.resolve())
    if not seeds:
        raise SystemExit("no seed logged an evaluation: nothing written")
    goal = f"{args.thresholds[0]:g}"
    to_goal = sorted(
        math.inf if s["to_goal"][goal]["seconds"] is None else s["to_goal"][goal]["seconds"]
        for s in seeds
    )
    median = statistics.median(to_goal)
    payload = {
        **header,
        "recipe_command": shlex.join(example),
        "inductor_cache": cache,
        "minutes": args.minutes,
        "eval_every": args.eval_every,
        "thresholds": args.thresholds,
        "processes": args.processes,
        "stop_at_goal": args.stop_at_goal,
        "resumed": args.resume,
        "interrupted": interrupted,
        "seeds": seeds,
        "env_steps_per_s": statistics.median(s["env_steps_per_s"] for s in seeds),
        "median_seconds_to_goal": None if median == math.inf else median,
        "seeds_at_goal": sum(value != math.inf for value in to_goal),
    }
    write_results(args.out, payload)
    seconds = "not reached" if median == math.inf else f"{median:.0f} s"
    print(
        f"median over {len(seeds)} seed(s): {payload['env_steps_per_s']:,.0f} env-steps/s, "
        f"{seconds} to {goal} ({payload['seeds_at_goal']} seed(s) reached it); wrote {args.out}"
    )
    if interrupted:
        raise SystemExit(130)


if __name__ == "__main__":
    main()
