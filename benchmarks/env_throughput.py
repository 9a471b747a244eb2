"""Environment throughput: env-steps/s (decisions, action repeat included) against num_envs.

At every size the simulator's step (``Simulator.step`` with a fixed action tensor) is timed both
ways of launching the substeps (``fuse_substeps``: a tick's substeps in one launch, or a launch
each); its default picks one by size, and the table's *simulator* column is the default's. Then
the TorchRL environment (``env.step_and_maybe_reset``, what collectors call, including the key
plumbing and resets). Prints a table and writes JSON (after every size).

    python benchmarks/env_throughput.py --device cuda --profile 65536
    python benchmarks/env_throughput.py --device cpu --num-envs 1 64 --seconds 2
    python benchmarks/env_throughput.py --device cuda --num-envs 65536 --actuator surface_flow
    python benchmarks/env_throughput.py --device cuda --num-envs 65536 --camera-resolution 64 \
        --profile

``--camera-resolution R`` renders the overhead camera (R x R) at every step and writes its
own JSON (``..._camera64.json``); its profile adds the camera's kernels up
(``camera_ms_per_step``): the camera's share of a step.

``--profile N ...`` then adds, at each size N (each measured size if none is given), the GPU
time and launch count of every kernel over eager (non-graph) steps, both ways of launching the
substeps: where a step's time goes.
"""

from __future__ import annotations

import subprocess
import time
from pathlib import Path

import torch
import warp as wp
from common import benchmark_parser, run_header, table_header, table_row, write_results

from terrashift_rl.envs import GROUP, TerraShiftEnv
from terrashift_rl.sim import ACTUATORS, Simulator, TerraShiftConfig, camera

DEFAULT_SIZES = [1, 4, 16, 64, 256, 1024, 4096, 16384, 65536]
CAMERA_KERNELS = {kernel.key for kernel in camera.KERNELS}
LAUNCHES = {True: "fused", False: "per_substep"}
"""JSON names of the two ways of launching the substeps, by ``fuse_substeps``."""


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


def cold_start(config: TerraShiftConfig, num_envs: int, device: torch.device) -> float:
    """Seconds from building the process's first simulator to the end of its first step."""
    _sync(device)
    start = time.perf_counter()
    sim = Simulator(config, num_envs=num_envs, device=device, seed=0)
    sim.reset()
    sim.step(torch.zeros(sim.action_shape, device=device))
    _sync(device)
    return time.perf_counter() - start


def measure(config: TerraShiftConfig, num_envs: int, device: torch.device, seconds: float) -> dict:
    k = config.num_agents
    generator = torch.Generator(device=device).manual_seed(0)
    action = torch.rand(num_envs, k, 6, device=device, generator=generator) * 2 - 1

    row = {"num_envs": num_envs}
    for fused in (True, False):
        sim = Simulator(config, num_envs=num_envs, device=device, seed=0, fuse_substeps=fused)
        sim.reset()
        row[f"sim_steps_per_s_{LAUNCHES[fused]}"] = _rate(
            lambda sim=sim: sim.step(action), num_envs, device, seconds, warmup=5
        )
        del sim

    env = TerraShiftEnv(config, num_envs=num_envs, device=device, seed=0)
    state = {"td": env.reset()}

    def env_step() -> None:
        td = state["td"]
        td.set((GROUP, "action"), action)
        _, state["td"] = env.step_and_maybe_reset(td)

    row["fuse_substeps"] = env.sim.fuse_substeps  # what a default simulator does at this size
    row["sim_steps_per_s"] = row[f"sim_steps_per_s_{LAUNCHES[env.sim.fuse_substeps]}"]
    row["env_steps_per_s"] = _rate(env_step, num_envs, device, seconds, warmup=5)
    return row


def profile(config: TerraShiftConfig, num_envs: int, device: torch.device, fused: bool) -> dict:
    """GPU milliseconds and launches per step of each kernel, from eager launches (CUDA only)."""
    steps = 10
    sim = Simulator(
        config, num_envs=num_envs, device=device, seed=0, cuda_graph=False, fuse_substeps=fused
    )
    sim.reset()
    action = torch.zeros(sim.action_shape, device=device)
    for _ in range(3):
        sim.step(action)
    wp.timing_begin(cuda_filter=wp.TIMING_KERNEL)
    for _ in range(steps):
        sim.step(action)
    results = wp.timing_end()
    per_kernel: dict[str, dict] = {}
    for result in results:
        # "forward kernel <name>_<hash>": the kernel's name is what the docs cite
        name = result.name.split()[-1].rsplit("_", 1)[0]
        entry = per_kernel.setdefault(name, {"ms": 0.0, "launches": 0})
        entry["ms"] += result.elapsed
        entry["launches"] += 1
    for entry in per_kernel.values():
        entry["ms"] /= steps
        entry["launches"] //= steps
    return dict(sorted(per_kernel.items(), key=lambda item: -item[1]["ms"]))


def _commit() -> str | None:
    """The measured code's commit, if it runs from a git checkout."""
    try:
        return subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"],
            cwd=Path(__file__).parent,
            capture_output=True,
            text=True,
            check=True,
        ).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return None


def main() -> None:
    parser = benchmark_parser(__doc__, device=True)
    parser.add_argument("--num-envs", type=int, nargs="+", default=DEFAULT_SIZES)
    parser.add_argument("--seconds", type=float, default=2.0, help="timing window per size")
    parser.add_argument("--column-shape", default="ellipsoid")
    parser.add_argument("--actuator", default="wavelets", choices=sorted(ACTUATORS))
    parser.add_argument(
        "--camera-resolution", type=int, default=0, help="camera pixels per side (0: no camera)"
    )
    parser.add_argument("--out", type=Path, default=None, help="JSON path (default by device)")
    parser.add_argument(
        "--profile",
        type=int,
        nargs="*",
        metavar="N",
        help="time every kernel at these sizes, at every measured size if none (CUDA only)",
    )
    args = parser.parse_args()
    profile_sizes = [] if args.profile is None else args.profile or args.num_envs

    device = torch.device(args.device)
    if profile_sizes and device.type != "cuda":
        parser.error("--profile times GPU kernels: it needs --device cuda")
    config = TerraShiftConfig.preset(
        "pretrain",
        column_shape=args.column_shape,
        actuator=args.actuator,
        camera_resolution=args.camera_resolution,
    )
    family = "" if args.actuator == "wavelets" else f"_{args.actuator}"
    suffix = f"_camera{config.camera_resolution}" if config.camera_resolution else ""
    default_out = f"env_throughput_{device.type}{family}{suffix}.json"
    out = args.out or Path(__file__).parent / "results" / default_out
    payload = {
        "benchmark": "env_throughput",
        **run_header(device),
        "warp": wp.__version__,
        "commit": _commit(),
        "config": {
            "preset": "pretrain",
            "column_shape": config.column_shape,
            "actuator": config.actuator,
            "substeps": config.substeps,
            "action_repeat": config.action_repeat,
            "camera_resolution": config.camera_resolution,
        },
        "rows": [],
        "profiles": [],
    }
    wp.init()
    cache = Path(wp.config.kernel_cache_dir)
    payload["kernel_cache_entries_before"] = len(list(cache.iterdir())) if cache.is_dir() else 0
    torch.zeros(1, device=device)  # the device's context exists before the clock starts
    payload["cold_start_s"] = cold_start(config, args.num_envs[0], device)
    camera = f", {config.camera_resolution}^2 camera" if config.camera_resolution else ""
    print(
        f"TerraShift env throughput (env-steps/s), pretrain scene ({config.actuator}, "
        f"{config.column_shape}{camera}), {payload['device']}"
    )
    print(
        f"cold start: {payload['cold_start_s']:.1f} s (first simulator, {args.num_envs[0]:,} "
        f"environments, built to its first step; {payload['kernel_cache_entries_before']} "
        "kernel cache entries before)"
    )
    print(
        table_header(["num_envs", "simulator", "substeps", "fused", "per substep", "TorchRL env"])
    )
    for n in args.num_envs:
        row = measure(config, n, device, args.seconds)
        payload["rows"].append(row)
        write_results(out, payload)
        print(
            table_row(
                [
                    f"{n:,}",
                    f"{row['sim_steps_per_s']:,.0f}",
                    LAUNCHES[row["fuse_substeps"]],
                    f"{row['sim_steps_per_s_fused']:,.0f}",
                    f"{row['sim_steps_per_s_per_substep']:,.0f}",
                    f"{row['env_steps_per_s']:,.0f}",
                ]
            )
        )
    for n in profile_sizes:
        for fused in (True, False):
            kernels = profile(config, n, device, fused)
            record = {"num_envs": n, "fuse_substeps": fused, "kernel_ms_per_step": kernels}
            total = sum(entry["ms"] for entry in kernels.values())
            camera_ms = sum(kernels[name]["ms"] for name in CAMERA_KERNELS & kernels.keys())
            if config.camera_resolution:
                record["camera_ms_per_step"] = camera_ms
            payload["profiles"].append(record)
            write_results(out, payload)
            print(f"\nkernels per step at {n} environments, substeps {LAUNCHES[fused]}:")
            print(table_header(["kernel", "ms / step", "share", "launches"]))
            for kernel, entry in kernels.items():
                share = f"{100 * entry['ms'] / total:.1f}%"
                print(table_row([kernel, f"{entry['ms']:.3f}", share, entry["launches"]]))
            if config.camera_resolution:
                share = f"{100 * camera_ms / total:.1f}%"
                print(table_row(["camera (draw_*)", f"{camera_ms:.3f}", share, ""]))
            print(table_row(["total", f"{total:.3f}", "", ""]))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
