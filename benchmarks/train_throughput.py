"""End-to-end training throughput: OnPolicyTrainer iterations, collection and update together.

Each setting (environments, epochs, mini-batches, precision, execution) trains the network
(``--preset``, with ``--model`` fields replaced) on the pretrain scene for ``--warmup`` untimed
iterations (compilation and the first allocations happen there), then ``--iters`` timed ones.
Reported per setting: env-steps/s of whole iterations, collection alone, and how an
iteration's seconds split into collection, the value-estimation pass and the epochs. Prints a
table and writes JSON.

    python benchmarks/train_throughput.py --device cuda
    python benchmarks/train_throughput.py --settings 2048:2:8:fp32:graphs 2048:2:8:fp32:eager
    python benchmarks/train_throughput.py --device cpu --settings 8:1:2:fp32:eager --preset small
    python benchmarks/train_throughput.py --settings 2048:2:8:tf32:graphs --model embed_dim=64
    python benchmarks/train_throughput.py --settings 2048:2:8:tf32:graphs --deterministic
    python benchmarks/train_throughput.py --settings 2048:2:8:tf32:eager --profile 25

``--profile N`` runs one more iteration per setting under ``torch.profiler`` and prints its N
operators of most device time (CPU time on CPU), which go into the JSON too. Profile eager
settings: kernels replayed from a CUDA graph are not attributed to operators.
"""

from __future__ import annotations

import argparse
import ast
import dataclasses
import statistics
import time
from pathlib import Path

import torch
from common import benchmark_parser, device_name, run_header, write_results
from torch.autograd import DeviceType

from terrashift_rl.modules import TerraShiftModelConfig, make_terrashift_networks
from terrashift_rl.sim import TerraShiftConfig
from terrashift_rl.training import OnPolicyTrainer, TrainConfig, make_trainer, make_training_env

PRECISIONS = ("fp32", "tf32", "bf16")  # tf32: float32 with TensorFloat-32 matrix products
# compiled: torch.compile without CUDA graphs; compiled-graphs: compiled networks replayed in them
EXECUTIONS = ("eager", "graphs", "compiled", "compiled-graphs")
DEFAULT_SETTINGS = [
    "2048:2:8:fp32:graphs",  # the default recipe
    "2048:2:8:fp32:eager",
    "4096:2:8:fp32:eager",
    "4096:2:8:bf16:compiled",
    "8192:1:4:bf16:compiled",
    "16384:1:8:bf16:compiled",
]


def parse_setting(text: str) -> dict:
    """``envs:epochs:minibatches:precision:execution``, e.g. ``2048:2:8:fp32:graphs``."""
    parts = text.split(":")
    if len(parts) != 5 or parts[3] not in PRECISIONS or parts[4] not in EXECUTIONS:
        raise argparse.ArgumentTypeError(
            f"setting {text!r} is not envs:epochs:minibatches:"
            f"({'|'.join(PRECISIONS)}):({'|'.join(EXECUTIONS)})"
        )
    try:
        envs, epochs, minibatches = (int(part) for part in parts[:3])
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"setting {text!r}: envs, epochs, minibatches are integers"
        ) from None
    return {
        "num_envs": envs,
        "epochs": epochs,
        "minibatches": minibatches,
        "precision": parts[3],
        "execution": parts[4],
    }


def parse_model_field(text: str) -> tuple[str, object]:
    """``field=value`` of TerraShiftModelConfig, the value a Python literal: ``embed_dim=64``."""
    field, sep, value = text.partition("=")
    fields = {f.name for f in dataclasses.fields(TerraShiftModelConfig)}
    if not sep or field not in fields:
        raise argparse.ArgumentTypeError(
            f"{text!r} is not FIELD=VALUE with FIELD one of TerraShiftModelConfig's: "
            + ", ".join(sorted(fields))
        )
    try:
        return field, ast.literal_eval(value)
    except (ValueError, SyntaxError):
        raise argparse.ArgumentTypeError(f"{text!r}: {value!r} is not a Python literal") from None


def measure(setting: dict, args: argparse.Namespace, device: torch.device) -> dict:
    torch.manual_seed(0)
    model = TerraShiftModelConfig.small() if args.preset == "small" else TerraShiftModelConfig()
    model = dataclasses.replace(model, **args.model)
    networks = make_terrashift_networks(model).to(device)
    config = TrainConfig(
        num_envs=setting["num_envs"],
        epochs=setting["epochs"],
        minibatches=setting["minibatches"],
        bf16=setting["precision"] == "bf16",
        tf32=setting["precision"] != "fp32",
        compile=setting["execution"].startswith("compiled"),
        cuda_graphs=setting["execution"].endswith("graphs"),
        deterministic=args.deterministic,
    )
    env = make_training_env(
        TerraShiftConfig.preset("pretrain"),
        networks,
        num_envs=config.num_envs,
        device=device,
        seed=0,
    )
    trainer = make_trainer(env, networks, config)
    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats(device)
    start = time.perf_counter()
    for _ in range(args.warmup):
        trainer.train_iteration()
    warmup_seconds = time.perf_counter() - start
    rows = [trainer.train_iteration() for _ in range(args.iters)]
    frames = config.num_envs * config.steps_per_iteration

    def median(name: str) -> float:
        return statistics.median(row[name] for row in rows)

    result = {
        **setting,
        "steps_per_iteration": config.steps_per_iteration,
        "warmup_iterations": args.warmup,
        "warmup_seconds": warmup_seconds,
        "env_steps_per_s": median("env_steps_per_s"),
        "collection_steps_per_s": median("collection_steps_per_s"),
        "collection_seconds": frames / median("collection_steps_per_s"),
        "estimation_seconds": median("estimation_seconds"),
        "epochs_seconds": median("update_seconds") - median("estimation_seconds"),
        "iteration_seconds": frames / median("env_steps_per_s"),
    }
    if device.type == "cuda":
        result["peak_memory_mb"] = torch.cuda.max_memory_allocated(device) / 2**20
    if args.profile:
        result["profile"] = profile_iteration(trainer, device, args.profile)
    return result


def profile_iteration(trainer: OnPolicyTrainer, device: torch.device, rows: int) -> list[dict]:
    """One more iteration under torch.profiler; prints and returns its costliest operators.

    On CUDA an operator's time is that of the kernels it launched, its share that of all
    kernel time in the iteration.
    """
    cpu = torch.profiler.ProfilerActivity.CPU
    activities = [cpu, torch.profiler.ProfilerActivity.CUDA] if device.type == "cuda" else [cpu]
    with torch.profiler.profile(activities=activities) as profiler:
        trainer.train_iteration()
    averages = profiler.key_averages()
    sort_by = "self_device_time_total" if device.type == "cuda" else "self_cpu_time_total"
    print(averages.table(sort_by=sort_by, row_limit=rows))
    events = [event for event in averages if not event.is_user_annotation]
    operators = [event for event in events if event.device_type == DeviceType.CPU]
    kernels = [event for event in events if event.device_type == DeviceType.CUDA]
    measured = kernels or operators
    total = sum(getattr(event, sort_by) for event in measured)
    top = sorted(operators, key=lambda event: getattr(event, sort_by), reverse=True)[:rows]
    return [
        {
            "operator": event.key,
            "calls": event.count,
            "self_ms": getattr(event, sort_by) / 1e3,
            "share": getattr(event, sort_by) / total,
        }
        for event in top
    ]


def format_row(row: dict) -> str:
    name = (
        f"{row['num_envs']:>6} | {row['epochs']}x{row['minibatches']:<3} | {row['precision']} | "
        f"{row['execution']:>8}"
    )
    return (
        f"{name} | {row['env_steps_per_s']:>10,.0f} | {row['collection_steps_per_s']:>10,.0f} | "
        f"{row['collection_seconds']:>6.2f} | {row['estimation_seconds']:>6.2f} | "
        f"{row['epochs_seconds']:>6.2f} | {row['warmup_seconds']:>7.1f}"
    )


def main() -> None:
    parser = benchmark_parser(__doc__, device=True)
    parser.add_argument(
        "--settings", type=parse_setting, nargs="+", default=[*map(parse_setting, DEFAULT_SETTINGS)]
    )
    parser.add_argument("--warmup", type=int, default=3, help="untimed iterations per setting")
    parser.add_argument("--iters", type=int, default=4, help="timed iterations per setting")
    parser.add_argument("--preset", choices=["default", "small"], default="default")
    parser.add_argument(
        "--model",
        type=parse_model_field,
        nargs="+",
        default=[],
        metavar="FIELD=VALUE",
        help="network fields that replace the preset's, e.g. embed_dim=64 cnn_channels=[8,16,16]",
    )
    parser.add_argument(
        "--deterministic",
        action="store_true",
        help="deterministic algorithms only (train.deterministic), for every setting",
    )
    parser.add_argument(
        "--profile",
        type=int,
        default=0,
        metavar="N",
        help="profile one more iteration per setting and print its N costliest operators",
    )
    parser.add_argument(
        "--out", type=Path, default=Path(__file__).parent / "results" / "train_throughput.json"
    )
    args = parser.parse_args()
    args.model = dict(args.model)
    if args.warmup < 0 or args.iters < 1 or args.profile < 0:
        parser.error("--warmup must be >= 0, --iters >= 1 and --profile >= 0")
    device = torch.device(args.device)
    name = device_name(device)
    fields = "".join(f" {field}={value}" for field, value in args.model.items())
    mode = ", deterministic algorithms" if args.deterministic else ""
    print(
        f"MA-POCA training throughput, pretrain scene, {args.preset} network{fields}{mode}, {name}"
    )
    print(
        "  envs | ep x mb | prec |     exec | env-steps/s |  collect/s | coll s | est s  |"
        " epochs s | warmup s"
    )
    payload = {
        **run_header(device),
        "preset": args.preset,
        "model": args.model,
        "deterministic": args.deterministic,
        "rows": [],
    }
    for setting in args.settings:
        payload["rows"].append(measure(setting, args, device))
        print(format_row(payload["rows"][-1]), flush=True)
        write_results(args.out, payload)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
