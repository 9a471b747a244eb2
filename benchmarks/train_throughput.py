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

``--recipe`` times instead the pretraining recipe's own setting (its scene, network and
training settings, with ``--overrides``), as one more row.

    python benchmarks/train_throughput.py --recipe --overrides train.steps_per_iteration=32

``--parts`` profiles instead one update of the pretraining recipe's own setting (its scene,
network and training settings, with ``--overrides``), eagerly, after ``--warmup`` iterations:
the device time of each network part's forward and backward passes (backward kernels are
matched to the forward operation that recorded them), of the loss's other work, gradient
clipping, the AdamW step and the value-estimation pass, and the host synchronisations.

    python benchmarks/train_throughput.py --parts --warmup 2 --out results/update_parts.json
"""

from __future__ import annotations

import argparse
import collections
import dataclasses
import functools
import statistics
import time
from pathlib import Path

import torch
from common import (
    benchmark_parser,
    device_name,
    field_parser,
    inductor_cache,
    run_header,
    write_results,
)
from hydra import compose, initialize_config_dir
from torch.autograd import DeviceType

from terrashift_rl.modules import TerraShiftModelConfig, make_terrashift_networks
from terrashift_rl.sim import TerraShiftConfig
from terrashift_rl.training import OnPolicyTrainer, TrainConfig, make_trainer, make_training_env
from terrashift_rl.training.launch import close_compile_workers
from terrashift_rl.training.settings import RecipeConfig, register_config_schemas

CONFIGS = Path(__file__).resolve().parents[1] / "recipes" / "configs"
PARTS = {
    "heightmap_encoder": "heightmap encoder (CNN)",
    "object_encoder": "object encoder",
    "agent_encoder": "agent encoder",
    "cross_attention": "cross-attention",
    "self_attention": "self-attention",
    "feed_forward": "trunk feed-forward",
    "output_mlp": "trunk output MLP",
    "memory": "GRU memory",
    "policy_head": "policy head",
    "value_head": "value head",
    "baseline_head": "baseline head",
}
"""The network parts ``--parts`` reports: the last name of a module's path, and its label."""
PHASES = {
    "value estimation": "value-estimation pass",
    "Optimizer.step#AdamW.step": "AdamW step",
    "clipping and step": "gradient norm and clipping",
}
"""Profiler ranges (innermost first wins) and the rows they give."""
SYNCHRONISATIONS = (
    "cudaStreamSynchronize",
    "cudaDeviceSynchronize",
    "cudaEventSynchronize",
    "aten::_local_scalar_dense",  # .item(), bool(tensor)
    "aten::nonzero",  # boolean indexing: its output's size
)
"""Profiled events that make the host wait for the device (the scalar reads only where the
scalar is on the device)."""

PRECISIONS = ("fp32", "tf32", "bf16")  # tf32: float32 with TensorFloat-32 matrix products
# compiled: torch.compile without CUDA graphs; compiled-graphs: compiled networks replayed in them
EXECUTIONS = ("eager", "graphs", "compiled", "compiled-graphs")
DEFAULT_SETTINGS = [
    "2048:2:8:fp32:graphs",  # TrainConfig's batch (--recipe times the recipe's own setting)
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
    return {**setting, **time_iterations(make_trainer(env, networks, config), args)}


def time_iterations(trainer: OnPolicyTrainer, args: argparse.Namespace) -> dict:
    """``args.warmup`` untimed iterations of ``trainer``, then the medians of ``args.iters``
    timed ones (and ``--profile``'s operators)."""
    device, config = trainer.device, trainer.config
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


def recipe_trainer(overrides: list[str], device: torch.device) -> OnPolicyTrainer:
    """A trainer with the pretraining recipe's scene, network and training settings, its
    networks initialised from seed 0 as ``measure``'s are."""
    torch.manual_seed(0)
    register_config_schemas()
    with initialize_config_dir(config_dir=str(CONFIGS), version_base=None):
        settings = RecipeConfig.of(compose(config_name="mapoca_pretrain", overrides=overrides))
    networks = make_terrashift_networks(settings.model).to(device)
    env = make_training_env(
        settings.env, networks, num_envs=settings.train.num_envs, device=device, seed=0
    )
    return make_trainer(env, networks, settings.train)


def labelled(label: str, function):
    """``function`` inside a profiler range named ``label``."""

    @functools.wraps(function)
    def inside(*args, **kwargs):
        with torch.profiler.record_function(label):
            return function(*args, **kwargs)

    return inside


def profile_update_parts(trainer: OnPolicyTrainer) -> dict:
    """One eager update of a freshly collected batch under torch.profiler, its kernel time by
    network part (forward, and backward matched through the autograd sequence numbers), by
    phase, and the host synchronisations (prints a table)."""
    data = trainer.collect()
    trainer.algorithm = dataclasses.replace(
        trainer.algorithm, estimate=labelled("value estimation", trainer.algorithm.estimate)
    )
    trainer._step = labelled("clipping and step", trainer._step)
    trainer._update_steps = {}
    ranges = collections.defaultdict(list)
    handles = []
    for name, module in trainer.networks.named_modules():
        part = PARTS.get(name.rsplit(".", 1)[-1])
        if part is None:
            continue

        def enter(module, args, label=f"forward: {part}"):
            ranges[id(module)].append(torch.profiler.record_function(label).__enter__())

        def leave(module, args, output):
            ranges[id(module)].pop().__exit__(None, None, None)

        handles += [module.register_forward_pre_hook(enter), module.register_forward_hook(leave)]
    activities = [torch.profiler.ProfilerActivity.CPU]
    if trainer.device.type == "cuda":
        activities.append(torch.profiler.ProfilerActivity.CUDA)
    try:
        with torch.profiler.profile(activities=activities) as profiler:
            start = time.perf_counter()
            trainer.update(data)
            seconds = time.perf_counter() - start
    finally:
        for handle in handles:
            handle.remove()
    events = profiler.events()

    def enclosing(event) -> list:
        chain = []
        while event is not None:
            chain.append(event)
            event = event.cpu_parent
        return chain

    # forward operations' sequence numbers, by the part whose range holds them
    part_of_sequence = {}
    for event in events:
        if event.sequence_nr < 0 or event.is_user_annotation:
            continue
        for outer in enclosing(event):
            if outer.name.startswith("forward: "):
                part_of_sequence.setdefault(event.sequence_nr, outer.name[len("forward: ") :])
                break
    rows = collections.Counter()
    on_cuda = trainer.device.type == "cuda"  # else operators' own CPU time
    for event in events:
        kernel_us = event.self_device_time_total if on_cuda else event.self_cpu_time_total
        if event.device_type != DeviceType.CPU or event.is_user_annotation or kernel_us <= 0:
            continue
        chain = enclosing(event)
        names = [outer.name for outer in chain]
        phase = next((PHASES[name] for name in names if name in PHASES), None)
        forward = next((name for name in names if name.startswith("forward: ")), None)
        backward = next(
            (
                part_of_sequence.get(outer.sequence_nr, "other")
                for outer in chain
                if "Backward" in outer.name and outer.sequence_nr >= 0
            ),
            None,
        )
        if phase is not None:
            rows[phase] += kernel_us
        elif forward is not None:
            rows[f"{forward[len('forward: ') :]}, forward"] += kernel_us
        elif backward is not None:
            rows[f"{backward}, backward"] += kernel_us
        else:
            rows["other (loss arithmetic, indexing, copies)"] += kernel_us
    total = sum(rows.values())

    def place(event) -> str:
        in_pass = any(outer.name == "value estimation" for outer in enclosing(event))
        return "the estimation pass" if in_pass else "the rest"

    # by where they happen; in the rest, an eager AdamW reads its step counts, which live on the
    # CPU and wait for nothing
    counts = collections.Counter(
        f"{event.name} in {place(event)}" for event in events if event.name in SYNCHRONISATIONS
    )
    print(f"one update, eager: {total / 1e3:.1f} ms of kernels, {seconds:.2f} s under the profiler")
    for name, kernel_us in rows.most_common():
        print(f"  {name:<45} {kernel_us / 1e3:>8.1f} ms  {kernel_us / total:>6.1%}")
    print(f"  host synchronisations: {dict(counts)}")
    return {
        "kernel_ms": total / 1e3,
        "profiled_seconds": seconds,
        "minibatch_updates": trainer.config.epochs * trainer.config.minibatches,
        "rows": [
            {"part": name, "kernel_ms": kernel_us / 1e3, "share": kernel_us / total}
            for name, kernel_us in rows.most_common()
        ],
        "host_synchronisations": dict(counts),
    }


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
        type=field_parser(TerraShiftModelConfig),
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
        "--parts",
        action="store_true",
        help="profile one update of the pretraining recipe's setting by network part",
    )
    parser.add_argument(
        "--recipe",
        action="store_true",
        help="time the pretraining recipe's own setting (its scene, network and training)",
    )
    parser.add_argument(
        "--overrides",
        nargs="+",
        default=[],
        metavar="KEY=VALUE",
        help="recipe overrides (--recipe, --parts)",
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
    if args.parts:
        profile_recipe_update(args, device, name)
        return
    if args.recipe:
        time_recipe(args, device, name)
        return
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
        "inductor_cache": inductor_cache(),
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


def time_recipe(args: argparse.Namespace, device: torch.device, name: str) -> None:
    """``--recipe``: the pretraining recipe's own trainer (with ``--overrides``) timed as a
    setting is."""
    cache = inductor_cache()
    trainer = recipe_trainer([f"run.device={device.type}", *args.overrides], device)
    print(f"pretraining recipe ({' '.join(args.overrides) or 'defaults'}), {name}")
    config, cuda = trainer.config, device.type == "cuda"
    row = {
        "num_envs": config.num_envs,
        "epochs": config.epochs,
        "minibatches": config.minibatches,
        "precision": "bf16" if config.bf16 and cuda else "tf32" if config.tf32 and cuda else "fp32",
        "execution": ("compiled-" if config.compile else "")
        + ("graphs" if config.cuda_graphs and cuda else "eager"),
        **time_iterations(trainer, args),
    }
    print(format_row(row))
    payload = {**run_header(device), "inductor_cache": cache, "overrides": args.overrides}
    write_results(args.out, {**payload, "rows": [row]})
    print(f"wrote {args.out}")


def profile_recipe_update(args: argparse.Namespace, device: torch.device, name: str) -> None:
    """``--parts``: warm-up iterations with the recipe's execution (CUDA graphs), then one
    update profiled eagerly on a trainer that continues from the same weights."""
    overrides = [f"run.device={device.type}", *args.overrides]
    trainer = recipe_trainer(overrides, device)
    print(f"pretraining recipe ({' '.join(args.overrides) or 'defaults'}), {name}")
    for _ in range(args.warmup):
        trainer.train_iteration()
    eager = recipe_trainer([*overrides, "train.cuda_graphs=false"], device)
    eager.load_state_dict(trainer.state_dict())
    payload = {
        **run_header(device),
        "overrides": args.overrides,
        "warmup_iterations": args.warmup,
        "parts": profile_update_parts(eager),
    }
    write_results(args.out, payload)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    try:
        main()
    finally:
        close_compile_workers()  # not the minutes Inductor may wait for them at exit
