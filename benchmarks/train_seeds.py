"""Trains one recipe over several seeds at once, spread over the GPUs, and summarises each run.

    python benchmarks/train_seeds.py --name position --seeds 0 1 2 3 4 5 --gpus 2 \
        --minutes 7.5 --root /tmp/runs -- env.action_mode=position run.eval_every=25
    python benchmarks/train_seeds.py --name position --seeds 0 1 2 3 4 5 --gpus 2 \
        --minutes 7.5 --root /tmp/runs --resume -- env.action_mode=position run.eval_every=25

Run ``s`` is ``python recipes/<recipe>.py <overrides> run.seed=s logger=csv`` in its own
process, in ``<root>/<name>_seed<s>_part<p>``; the i-th seed's on GPU ``i mod gpus``
(``CUDA_VISIBLE_DEVICES``; with ``--gpus 0`` every run uses the recipe's default device, so
``CUDA_VISIBLE_DEVICES=2 python benchmarks/train_seeds.py --gpus 0 ...`` keeps one command's
seeds on GPU 2 while other commands use the other GPUs).
Several runs share a GPU, so compare them by env-steps, not by wall-clock time. ``--resume``
starts part ``p + 1`` of each seed from the last checkpoint of its newest part, so that runs
longer than one sitting continue exactly (``run.resume``). When every run has stopped, each
part's logs are summarised (``compact_logs.py``) into
``<out-dir>/<device>_<date>_<name>_seed<s>[_part<p>].json`` with the device's name and the
date (``<device>``: ``h100``, ``h200``, ..., or ``cpu``). Ctrl-C or SIGTERM reaches every run
once: each finishes its iteration and writes a checkpoint to resume from. The exit status is
that of the first run that failed, if any.
"""

from __future__ import annotations

import argparse
import os
import re
import signal
import subprocess
import sys
from datetime import date
from pathlib import Path

import torch
from common import benchmark_parser, device_name
from compact_logs import summarize, write_summary

ROOT = Path(__file__).resolve().parent.parent


def device_prefix(device: torch.device) -> str:
    """``cpu``, or the GPU's model in lower case: ``h100`` for "NVIDIA H100 80GB HBM3"."""
    if device.type != "cuda":
        return "cpu"
    name = device_name(device)
    match = re.search(r"\b([A-Z]\d{2,4})\b", name)
    return (match.group(1) if match else name.split()[-1]).lower()


def last_part(run_dir: Path) -> int | None:
    """The highest part number of the runs whose directories start with ``run_dir``'s name."""
    parts = [
        int(path.name.rsplit("_part", 1)[1])
        for path in run_dir.parent.glob(f"{run_dir.name}_part*")
        if path.name.rsplit("_part", 1)[1].isdigit()
    ]
    return max(parts, default=None)


def command(args: argparse.Namespace, seed: int, run_dir: Path, resume: Path | None) -> list[str]:
    overrides = [*args.overrides, f"run.seed={seed}", "logger=csv", f"hydra.run.dir={run_dir}"]
    if args.minutes is not None:
        overrides.append(f"run.minutes={args.minutes}")
    if resume is not None:
        overrides.append(f"run.resume={resume}")
    return [sys.executable, str(ROOT / "recipes" / f"{args.recipe}.py"), *overrides]


def main() -> None:
    parser = benchmark_parser(__doc__)
    parser.add_argument("--name", required=True, help="names the runs and their summaries")
    parser.add_argument("--seeds", type=int, nargs="+", required=True)
    parser.add_argument("--gpus", type=int, default=torch.cuda.device_count())
    parser.add_argument("--recipe", default="mapoca_pretrain", help="a recipes/ script's name")
    parser.add_argument("--minutes", type=float, help="run.minutes of every run")
    parser.add_argument("--root", type=Path, default=Path("outputs") / "seeds")
    parser.add_argument("--resume", action="store_true", help="continue each seed's last part")
    parser.add_argument(
        "--out-dir", type=Path, default=ROOT / "benchmarks" / "results" / "training"
    )
    parser.add_argument("overrides", nargs="*", help="recipe overrides, after --")
    args = parser.parse_args()

    device = torch.device("cuda" if torch.cuda.is_available() else "cpu")
    processes = []
    for index, seed in enumerate(args.seeds):
        stem = args.root.resolve() / f"{args.name}_seed{seed}"
        previous = last_part(stem)
        if args.resume and previous is None:
            parser.error(f"--resume: no part of {stem.name} under {args.root}")
        if not args.resume and previous is not None:
            parser.error(f"{stem.name} has run under {args.root}: --resume continues it")
        part = previous + 1 if args.resume else 0
        resume = Path(f"{stem}_part{previous}") / "checkpoints" / "last.pt" if part else None
        run_dir = Path(f"{stem}_part{part}")
        env = dict(os.environ)
        if args.gpus:
            env["CUDA_VISIBLE_DEVICES"] = str(index % args.gpus)
        run_dir.mkdir(parents=True, exist_ok=True)
        log = open(run_dir / "train.log", "w")  # noqa: SIM115 (closed once the run ends)
        cmd = command(args, seed, run_dir, resume)
        print(" ".join(cmd), flush=True)
        # a session of its own: a signal reaches it once, forwarded below
        process = subprocess.Popen(
            cmd, env=env, stdout=log, stderr=subprocess.STDOUT, start_new_session=True
        )
        processes.append((seed, part, run_dir, log, process))

    def forward(signum: int, frame: object) -> None:
        """Ctrl-C or a scheduler's SIGTERM: every run finishes its iteration and checkpoints."""
        for *_, process in processes:
            process.send_signal(signum)

    for number in (signal.SIGINT, signal.SIGTERM):
        signal.signal(number, forward)
    status = 0
    today = date.today().isoformat()
    for seed, part, run_dir, log, process in processes:
        code = process.wait()
        log.close()
        status = status or code
        logged = sorted(run_dir.glob("logs/*/scalars/reward_per_decision.csv"))
        if not logged:
            print(f"seed {seed}: exit {code}, no logs (see {run_dir / 'train.log'})")
            continue
        suffix = f"_part{part}" if args.resume else ""
        name = f"{device_prefix(device)}_{today}_{args.name}_seed{seed}{suffix}"
        summary = summarize(
            logged[0].parent, name=name, points=48, tail=16, device=device_name(device), date=today
        )
        write_summary(summary, args.out_dir)
        last = summary["sparse"].get("eval_goal_fraction", [[None, None]])[-1]
        print(
            f"seed {seed}: exit {code}, {summary['iterations']} iterations, "
            f"last evaluation {last[1]} at {last[0]} env-steps -> {name}.json"
        )
    sys.exit(status)


if __name__ == "__main__":
    main()
