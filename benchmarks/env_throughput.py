"""Environment throughput: env-steps/s (decisions, action repeat included) against num_envs.

Two paths are timed at every size: the raw simulator step (``Simulator.step`` with a fixed
action tensor) and the TorchRL environment (``env.step_and_maybe_reset``, what collectors
call, including the key plumbing and resets). Prints a table and writes JSON.

    python benchmarks/env_throughput.py --device cuda
    python benchmarks/env_throughput.py --device cpu --num-envs 1 64 --seconds 2
    python benchmarks/env_throughput.py --device cuda --num-envs 65536 --profile

``--profile`` adds, for each size, the GPU time of every kernel over eager (non-graph) steps,
summed by kernel name: where a step's time goes.
"""

from __future__ import annotations

import argparse
import time
from datetime import date
from pathlib import Path

import torch
import warp as wp
from common import device_name, write_results

from terrashift_rl.envs import GROUP, TerraShiftEnv
from terrashift_rl.sim import Simulator, TerraShiftConfig

DEFAULT_SIZES = [1, 4, 16, 64, 256, 1024, 4096, 16384, 65536]


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def _rate(step, num_envs: int, device: torch.device, seconds: float, warmup: int) -> float:
    """Env-steps/s of ``step()``, timed over at least ``seconds`` after ``warmup`` calls."""
    for _ in range(warmup):
        step()
    _sync(device)
    calls, start = 0, time.perf_counter()
    while True:
        for _ in range(10):
            step()
        calls += 10
        _sync(device)
        elapsed = time.perf_counter() - start
        if elapsed >= seconds:
            return calls * num_envs / elapsed


def measure(config: TerraShiftConfig, num_envs: int, device: torch.device, seconds: float) -> dict:
    k = config.num_agents
    generator = torch.Generator(device=device).manual_seed(0)
    action = torch.rand(num_envs, k, 6, device=device, generator=generator) * 2 - 1

    sim = Simulator(config, num_envs=num_envs, device=device, seed=0)
    sim.reset()
    sim_rate = _rate(lambda: sim.step(action), num_envs, device, seconds, warmup=5)

    env = TerraShiftEnv(config, num_envs=num_envs, device=device, seed=0)
    state = {"td": env.reset()}

    def env_step() -> None:
        td = state["td"]
        td.set((GROUP, "action"), action)
        _, state["td"] = env.step_and_maybe_reset(td)

    env_rate = _rate(env_step, num_envs, device, seconds, warmup=5)
    return {"num_envs": num_envs, "sim_steps_per_s": sim_rate, "env_steps_per_s": env_rate}


def profile(config: TerraShiftConfig, num_envs: int, device: torch.device) -> dict:
    """GPU milliseconds per step of each kernel, from eager launches (CUDA only)."""
    steps = 10
    sim = Simulator(config, num_envs=num_envs, device=device, seed=0, cuda_graph=False)
    sim.reset()
    action = torch.zeros(sim.action_shape, device=device)
    for _ in range(3):
        sim.step(action)
    wp.timing_begin(cuda_filter=wp.TIMING_KERNEL)
    for _ in range(steps):
        sim.step(action)
    results = wp.timing_end()
    per_kernel: dict[str, float] = {}
    for result in results:
        name = result.name.split("_cuda_kernel")[0]
        per_kernel[name] = per_kernel.get(name, 0.0) + result.elapsed / steps
    return dict(sorted(per_kernel.items(), key=lambda item: -item[1]))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    parser.add_argument("--num-envs", type=int, nargs="+", default=DEFAULT_SIZES)
    parser.add_argument("--seconds", type=float, default=2.0, help="timing window per size")
    parser.add_argument("--column-shape", default="ellipsoid")
    parser.add_argument("--out", type=Path, default=None, help="JSON path (default by device)")
    parser.add_argument("--profile", action="store_true", help="per-kernel GPU time per step")
    args = parser.parse_args()

    device = torch.device(args.device)
    config = TerraShiftConfig.preset("pretrain", column_shape=args.column_shape)
    name = device_name(device)
    print(f"TerraShift env throughput, pretrain scene ({config.column_shape}), {name}")
    print(f"{'num_envs':>9} | {'simulator env-steps/s':>22} | {'TorchRL env env-steps/s':>24}")
    rows = []
    for n in args.num_envs:
        row = measure(config, n, device, args.seconds)
        rows.append(row)
        print(f"{n:>9} | {row['sim_steps_per_s']:>22,.0f} | {row['env_steps_per_s']:>24,.0f}")
        if args.profile and device.type == "cuda":
            row["kernel_ms_per_step"] = profile(config, n, device)
            total = sum(row["kernel_ms_per_step"].values())
            for name, ms in row["kernel_ms_per_step"].items():
                print(f"{'':>9}   {name:<40} {ms:8.3f} ms/step ({100 * ms / total:4.1f}%)")

    out = args.out or Path(__file__).parent / "results" / f"env_throughput_{device.type}.json"
    payload = {
        "benchmark": "env_throughput",
        "date": date.today().isoformat(),
        "device": name,
        "torch": torch.__version__,
        "config": {
            "preset": "pretrain",
            "column_shape": config.column_shape,
            "substeps": config.substeps,
            "action_repeat": config.action_repeat,
        },
        "rows": rows,
    }
    write_results(out, payload)
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
