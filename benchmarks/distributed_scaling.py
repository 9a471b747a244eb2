"""Data-parallel scaling: env-steps/s of the pretraining recipe on 1, 2, 4 and 8 GPUs of one host.

For each process count N that the host holds, launches

    torchrun --standalone --nproc_per_node=N recipes/mapoca_pretrain.py <recipe's defaults>

for ``--warmup`` + ``--iters`` iterations (every rank keeps the recipe's ``train.num_envs``, so
the global batch is N times one GPU's, and splits it into N x ``train.minibatches`` mini-batches,
so a step averages one GPU's mini-batch), without evaluation, best.pt or periodic checkpoints,
logging to CSV. Reported per N: the median over the timed iterations of the logged env-steps/s
(every rank's collected env-steps over its iteration's seconds, summed over the ranks), of
collection alone, and of the update's seconds; the speed-up over the first N measured and the
scaling efficiency (speed-up / N x that N); and the launch's wall-clock seconds (start-up,
warm-up and the final checkpoint included). Prints a table and writes JSON.

    python benchmarks/distributed_scaling.py                          # 1, 2, 4, 8 GPUs
    python benchmarks/distributed_scaling.py --overrides train=throughput model=medium
    python benchmarks/distributed_scaling.py --smoke --processes 1 2  # CPU, gloo, smoke config

A launch that has not finished after ``--launch-timeout`` seconds is stopped, and the end of
its output printed. Every process runs with ``OMP_NUM_THREADS=1`` unless the variable is set
(torchrun's default from 2 processes on, here for 1 too). ``--smoke`` runs the recipe's smoke
config (4 environments per process, tiny network) with ``--device cpu`` (gloo) by default: a
check that the launch works, not a measurement.
"""

from __future__ import annotations

import argparse
import os
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch
from common import benchmark_parser, device_name, read_series, run_header, write_results
from hydra import compose, initialize_config_dir

from terrashift_rl.training.settings import register_config_schemas

ROOT = Path(__file__).resolve().parents[1]
RECIPE = ROOT / "recipes" / "mapoca_pretrain.py"
# one checkpoint at the end, nothing else between iterations that rank 0 alone would do
QUIET = [
    "run.eval_every=null",
    "run.best_window=0",
    "run.snapshot_every=null",
    "run.checkpoint_every=1000000",
    "run.minutes=null",
    "logger=csv",
]


def batch_per_process(config_name: str, overrides: list[str]) -> tuple[int, int]:
    """``train.num_envs`` and ``train.steps_per_iteration`` of the recipe's config."""
    register_config_schemas()
    with initialize_config_dir(config_dir=str(RECIPE.parent / "configs"), version_base=None):
        cfg = compose(config_name=config_name, overrides=overrides)
    return cfg.train.num_envs, cfg.train.steps_per_iteration


def measure(processes: int, args: argparse.Namespace, folder: Path) -> dict:
    overrides = [f"run.device={args.device}", *args.overrides]
    num_envs, steps = batch_per_process(args.config_name, overrides)
    iterations = args.warmup + args.iters
    run_dir = folder / f"processes_{processes}"
    command = [
        sys.executable,
        "-m",
        "torch.distributed.run",
        "--standalone",
        f"--nproc_per_node={processes}",
        str(RECIPE),
        "--config-name",
        args.config_name,
        *QUIET,
        *overrides,
        f"run.total_env_steps={iterations * processes * num_envs * steps}",
        f"hydra.run.dir={run_dir}",
    ]
    # one thread per process at every N (torchrun's own default from N = 2 on), unless set
    env = {"OMP_NUM_THREADS": "1", **os.environ}
    log = folder / f"processes_{processes}.log"
    start = time.perf_counter()
    with log.open("w") as output:
        # a session of its own: on a timeout, torchrun and its ranks are stopped together
        launch = subprocess.Popen(
            command,
            cwd=folder,
            env=env,
            stdout=output,
            stderr=subprocess.STDOUT,
            start_new_session=True,
        )
        try:
            launch.wait(timeout=args.launch_timeout)
        except subprocess.TimeoutExpired:
            os.killpg(launch.pid, signal.SIGKILL)
            launch.wait()
    launch_seconds = time.perf_counter() - start
    if launch.returncode != 0:
        what = "timed out" if launch_seconds >= args.launch_timeout else "failed"
        raise SystemExit(f"{' '.join(command)} {what}:\n{log.read_text()[-6000:]}")
    (scalars,) = run_dir.glob("logs/*/scalars")

    def timed(metric: str) -> float:
        _, values = read_series(scalars, metric)
        if len(values) != iterations:
            raise SystemExit(f"{scalars} holds {len(values)} rows of {metric}, not {iterations}")
        return statistics.median(values[args.warmup :])

    return {
        "processes": processes,
        "num_envs_per_process": num_envs,
        "steps_per_iteration": steps,
        "env_steps_per_s": timed("env_steps_per_s"),
        "collection_steps_per_s": timed("collection_steps_per_s"),
        "update_seconds": timed("update_seconds"),
        "launch_seconds": launch_seconds,
    }


def format_row(row: dict) -> str:
    return (
        f"{row['processes']:>9} | {row['num_envs_per_process'] * row['processes']:>7} | "
        f"{row['env_steps_per_s']:>11,.0f} | {row['speedup']:>7.2f} | {row['efficiency']:>10.0%} "
        f"| {row['collection_steps_per_s']:>10,.0f} | {row['update_seconds']:>8.2f} | "
        f"{row['launch_seconds']:>8.1f}"
    )


def main() -> None:
    parser = benchmark_parser(__doc__)
    parser.add_argument("--processes", type=int, nargs="+", default=[1, 2, 4, 8])
    parser.add_argument("--device", choices=["cuda", "cpu"], default=None)
    parser.add_argument("--smoke", action="store_true", help="the smoke config, on the CPU")
    parser.add_argument("--warmup", type=int, default=5, help="untimed iterations per launch")
    parser.add_argument("--iters", type=int, default=20, help="timed iterations per launch")
    parser.add_argument(
        "--overrides", nargs="+", default=[], metavar="KEY=VALUE", help="more recipe overrides"
    )
    parser.add_argument(
        "--launch-timeout",
        type=float,
        default=900.0,
        help="seconds before a launch is stopped and reported (it never blocks the table)",
    )
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args()
    if args.warmup < 0 or args.iters < 1 or min(args.processes) < 1:
        parser.error("--warmup must be >= 0, --iters >= 1 and every process count >= 1")
    args.config_name = "smoke" if args.smoke else "mapoca_pretrain"
    if args.device is None:
        args.device = "cpu" if args.smoke or not torch.cuda.is_available() else "cuda"
    if args.out is None:
        name = "distributed_scaling_smoke" if args.smoke else f"distributed_scaling_{args.device}"
        args.out = Path(__file__).parent / "results" / f"{name}.json"
    device = torch.device(args.device)
    counts = sorted(set(args.processes))
    if device.type == "cuda":
        gpus = torch.cuda.device_count()
        if any(count > gpus for count in counts):
            print(f"this host has {gpus} GPU(s): skipping {[c for c in counts if c > gpus]}")
        counts = [count for count in counts if count <= gpus]
        if not counts:
            raise SystemExit("no process count fits this host's GPUs")
    name = device_name(device)
    overrides = " ".join(args.overrides) or "none"
    print(
        f"MA-POCA data-parallel scaling, recipe config {args.config_name} (overrides: "
        f"{overrides}), {name}, {args.iters} timed iterations after {args.warmup}"
    )
    print(
        "processes |    envs | env-steps/s | speedup | efficiency |  collect/s | update s |"
        " launch s"
    )
    payload = {
        **run_header(device),
        "device_count": torch.cuda.device_count() if device.type == "cuda" else os.cpu_count(),
        "config_name": args.config_name,
        "overrides": args.overrides,
        "warmup_iterations": args.warmup,
        "timed_iterations": args.iters,
        "rows": [],
    }
    with tempfile.TemporaryDirectory() as folder:
        for count in counts:
            row = measure(count, args, Path(folder))
            first = payload["rows"][0] if payload["rows"] else row
            row["speedup"] = row["env_steps_per_s"] / first["env_steps_per_s"]
            row["efficiency"] = row["speedup"] * first["processes"] / count
            payload["rows"].append(row)
            print(format_row(row), flush=True)
            write_results(args.out, payload)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
