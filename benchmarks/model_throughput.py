"""Model throughput: time per env-step of the TerraShift networks, collection and training.

Collection is the actor's forward pass on one step of ``batch`` environments, without autograd
(what a collector runs). Training is one loss-style pass on ``batch`` env-steps cut into
sequences of ``--sequence-length`` steps in torchrl's recurrent mode: the actor's distribution
(trunk + policy head), the value and baseline heads on the same embedding, and backward. Every
combination of batch size, precision (fp32, bf16 autocast) and compilation (eager,
``TerraShiftNetworks.compile_networks``, as the trainer's ``train.compile``) is timed; "1st call"
includes compilation.
Prints a table and writes JSON after every combination, so an interrupted sweep keeps its rows.

    python benchmarks/model_throughput.py --device cuda
    python benchmarks/model_throughput.py --device cpu --batches 8 --iters 2 --graphs eager
"""

from __future__ import annotations

import argparse
import math
import statistics
import time
from dataclasses import asdict
from pathlib import Path

import torch
from common import benchmark_parser, device_name, run_header, write_results
from tensordict import TensorDict
from tensordict.nn import InteractionType, set_interaction_type
from torchrl.modules import set_recurrent_mode

from terrashift_rl.modules import TerraShiftModelConfig, keys, make_terrashift_networks
from terrashift_rl.modules.networks import TerraShiftNetworks
from terrashift_rl.training.launch import close_compile_workers

DEFAULT_BATCHES = [1024, 2048, 4096, 8192, 16384]
PRECISIONS = {"fp32": None, "bf16": torch.bfloat16}


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def make_batch(
    batch_shape: tuple[int, ...],
    *,
    num_agents: int,
    num_objects: int,
    map_side: int,
    config: TerraShiftModelConfig,
    device: torch.device,
) -> TensorDict:
    """Random observations in the environment's layout, mid-episode, with a GRU state."""

    def uniform(*shape: int) -> torch.Tensor:
        return torch.rand(*batch_shape, *shape, device=device) * 2 - 1

    agents = TensorDict(
        {
            "observation": uniform(num_agents, 9),
            "mask": torch.ones(*batch_shape, num_agents, dtype=torch.bool, device=device),
            "action": uniform(num_agents, 6),
            "recurrent_state": torch.randn(
                *batch_shape, num_agents, config.gru_layers, config.embed_dim, device=device
            ),
        },
        [*batch_shape, num_agents],
    )
    return TensorDict(
        {
            "heightmap": uniform(1, map_side, map_side),
            "objects": uniform(num_objects, 9),
            "objects_mask": torch.ones(*batch_shape, num_objects, dtype=torch.bool, device=device),
            "is_init": torch.zeros(*batch_shape, 1, dtype=torch.bool, device=device),
            "agents": agents,
        },
        list(batch_shape),
        device=device,
    )


def build_networks(
    config: TerraShiftModelConfig, device: torch.device, *, compiled: bool
) -> TerraShiftNetworks:
    networks = make_terrashift_networks(config).to(device)
    if compiled:
        # as the trainer's train.compile: every stage but the GRU's loop over time
        networks.compile_networks()
    return networks


def collection_step(networks: TerraShiftNetworks, data: TensorDict):
    def step() -> None:
        with torch.no_grad(), set_interaction_type(InteractionType.RANDOM):
            networks.actor(data.copy())

    return step


def training_step(networks: TerraShiftNetworks, data: TensorDict):
    parameters = list(networks.parameters())

    def step() -> None:
        td = data.copy()
        with set_recurrent_mode(True):
            dist = networks.actor.get_dist(td)
            networks.value_head(td)
            networks.baseline_head(td)
        loss = (
            -dist.log_prob(td[keys.ACTION]).float().mean()
            - dist.entropy().float().mean()
            + td[keys.STATE_VALUE].float().square().mean()
            + td[keys.BASELINE].float().square().mean()
        )
        loss.backward()
        for parameter in parameters:
            parameter.grad = None

    return step


def time_step(
    step, device: torch.device, *, precision: torch.dtype | None, iters: int, warmup: int
):
    """(first-call seconds, median seconds per call) of ``step`` under the given autocast."""
    with torch.autocast(
        device.type, dtype=precision or torch.float32, enabled=precision is not None
    ):
        _sync(device)
        start = time.perf_counter()
        step()
        _sync(device)
        first_call = time.perf_counter() - start
        for _ in range(warmup):
            step()
        durations = []
        for _ in range(iters):
            _sync(device)
            start = time.perf_counter()
            step()
            _sync(device)
            durations.append(time.perf_counter() - start)
    return first_call, statistics.median(durations)


def measure(
    args: argparse.Namespace,
    config: TerraShiftModelConfig,
    device: torch.device,
    *,
    mode: str,
    batch: int,
    precision_name: str,
    compiled: bool,
) -> dict:
    torch.manual_seed(0)
    networks = build_networks(config, device, compiled=compiled)
    if mode == "collect":
        batch_shape = (batch,)
    else:
        sequence_length = math.gcd(batch, args.sequence_length)
        batch_shape = (batch // sequence_length, sequence_length)
    data = make_batch(
        batch_shape,
        num_agents=args.agents,
        num_objects=args.objects,
        map_side=args.map_side,
        config=config,
        device=device,
    )
    step = collection_step(networks, data) if mode == "collect" else training_step(networks, data)
    row = {
        "mode": mode,
        "precision": precision_name,
        "compiled": compiled,
        "batch": batch,
        "batch_shape": list(batch_shape),
    }
    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats(device)
    try:
        first_call, per_call = time_step(
            step, device, precision=PRECISIONS[precision_name], iters=args.iters, warmup=args.warmup
        )
    except torch.OutOfMemoryError:
        return {**row, "error": "out of memory"}
    row.update(
        first_call_s=first_call,
        ms_per_call=per_call * 1e3,
        us_per_env_step=per_call * 1e6 / batch,
        env_steps_per_s=batch / per_call,
    )
    if device.type == "cuda":
        row["peak_memory_mb"] = torch.cuda.max_memory_allocated(device) / 2**20
    return row


def format_row(row: dict) -> str:
    head = (
        f"{row['mode']:>7} | {row['precision']:>4} | {'yes' if row['compiled'] else 'no':>7} | "
        f"{row['batch']:>6}"
    )
    if "error" in row:
        return f"{head} | {row['error']}"
    memory = f"{row['peak_memory_mb']:>9,.0f}" if "peak_memory_mb" in row else f"{'-':>9}"
    return (
        f"{head} | {row['ms_per_call']:>9.2f} | {row['us_per_env_step']:>8.3f} | "
        f"{row['env_steps_per_s']:>12,.0f} | {row['first_call_s']:>8.1f} | {memory}"
    )


def main() -> None:
    parser = benchmark_parser(__doc__, device=True)
    parser.add_argument("--batches", type=int, nargs="+", default=DEFAULT_BATCHES)
    parser.add_argument(
        "--precisions", nargs="+", choices=list(PRECISIONS), default=list(PRECISIONS)
    )
    parser.add_argument(
        "--modes", nargs="+", choices=["collect", "train"], default=["collect", "train"]
    )
    parser.add_argument(
        "--graphs", nargs="+", choices=["eager", "compiled"], default=["eager", "compiled"]
    )
    parser.add_argument("--iters", type=int, default=20, help="timed calls per combination")
    parser.add_argument("--warmup", type=int, default=3, help="untimed calls after the first")
    parser.add_argument("--agents", type=int, default=8)
    parser.add_argument("--objects", type=int, default=4)
    parser.add_argument("--map-side", type=int, default=32)
    parser.add_argument("--sequence-length", type=int, default=32, help="training sequences")
    parser.add_argument("--preset", choices=["default", "small"], default="default")
    parser.add_argument(
        "--out", type=Path, default=Path(__file__).parent / "results" / "model_throughput.json"
    )
    args = parser.parse_args()

    device = torch.device(args.device)
    if device.type == "cuda":
        torch.backends.cuda.matmul.allow_tf32 = True
        torch.backends.cudnn.allow_tf32 = True
    config = TerraShiftModelConfig() if args.preset == "default" else TerraShiftModelConfig.small()
    name = device_name(device)
    print(
        f"TerraShift model throughput, {args.preset} model, {args.agents} agents, "
        f"{args.objects} objects, {args.map_side}x{args.map_side} map, {name}"
    )
    print(
        f"{'mode':>7} | {'prec':>4} | {'compile':>7} | {'batch':>6} | {'ms/call':>9} | "
        f"{'us/step':>8} | {'env-steps/s':>12} | {'1st call':>8} | {'peak MiB':>9}"
    )
    rows: list[dict] = []
    payload = {
        "benchmark": "model_throughput",
        **run_header(device),
        "task": {
            "agents": args.agents,
            "objects": args.objects,
            "map_side": args.map_side,
            "sequence_length": args.sequence_length,
        },
        "timing": {"iters": args.iters, "warmup": args.warmup, "statistic": "median"},
        "model": {"preset": args.preset, **asdict(config)},
        "rows": rows,
    }
    for mode in args.modes:
        for precision_name in args.precisions:
            for compiled in [graphs == "compiled" for graphs in args.graphs]:
                # Compiled code is reused across batch sizes: after the second size dynamo
                # marks the batch dim dynamic, so only the first rows' first calls compile.
                torch._dynamo.reset()
                for batch in args.batches:
                    row = measure(
                        args,
                        config,
                        device,
                        mode=mode,
                        batch=batch,
                        precision_name=precision_name,
                        compiled=compiled,
                    )
                    rows.append(row)
                    print(format_row(row), flush=True)
                    write_results(args.out, payload)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    try:
        main()
    finally:
        close_compile_workers()  # not the minutes Inductor may wait for them at exit
