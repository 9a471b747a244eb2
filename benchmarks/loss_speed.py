"""Loss speed: one update of MAPOCALoss against torchrl's MAPPOLoss on VMAS-shaped data.

One update is what a training iteration spends in the loss: the value-estimation pass on a
collected batch of ``--envs`` x ``--steps`` frames (60 x 100 = 6,000, VMAS's batch in
``benchmarks/vmas_parity.py``), then one epoch of mini-batches of ``--minibatch`` frames, each
a forward pass, backward and an Adam step. K agents observe 10 features and act in 2 dims.
Both losses share the actor of ``examples/mapoca_vs_mappo.py`` (a tanh-Normal MLP, 2 x 64);
MAPOCALoss has the README's critics, ``CentralValue(10, width=64, depth=1)`` and
``CounterfactualBaseline(10, 2, width=64, depth=1)``; MAPPOLoss its usual centralised
``MultiAgentMLP`` critic (2 x 128, ``--mlp-width``). Every measurement runs in a fresh process,
on one CPU thread by default (``--threads``), and memory and time are measured in separate ones.

Time per update is the median of ``--repeats`` updates after one warm-up, wall-clock and
processor time; the ratios are of processor time on CPU (steadier where other work shares the
processor), of wall-clock time on CUDA. The first update of the process (wall-clock, "first
s") is reported apart: with ``torch.compile`` it holds the compilation. Peak memory is what an
update holds at most beyond what was there before it, measured on the second update (the first
loads code and creates the optimiser's state): on CUDA ``torch.cuda.max_memory_allocated``;
on CPU the peak of the process's resident set (``VmHWM``, reset through
``/proc/self/clear_refs``) less the resident set before the update, with glibc giving back the
blocks of 64 KiB or more when they are freed. With ``--parts`` it also times (same clock) the
parts of one mini-batch step apart (forward and backward of each network, the rest of the loss,
the optimiser) and of the value-estimation pass.

    python benchmarks/loss_speed.py                      # CPU, K = 4 and 16
    python benchmarks/loss_speed.py --device cuda --parts
"""

from __future__ import annotations

import argparse
import os
import statistics
import time
from concurrent.futures import ProcessPoolExecutor
from datetime import date
from multiprocessing import get_context
from pathlib import Path

import torch
from common import device_name, write_results
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModule
from torch import nn
from torchrl.modules import MultiAgentMLP, NormalParamExtractor, ProbabilisticActor, TanhNormal
from torchrl.objectives import LossModule
from torchrl.objectives.multiagent import MAPPOLoss

from terrashift_rl.modules import (
    AttentionBaseline,
    CentralValue,
    CounterfactualBaseline,
    CounterfactualMLP,
    mlp_value,
)
from terrashift_rl.objectives import MAPOCALoss

OBSERVATION_DIM, ACTION_DIM = 10, 2
GROUP = "agents"
OBSERVATION, ACTION = (GROUP, "observation"), (GROUP, "action")
METHODS = (
    "MAPOCA",
    "MAPOCA, one pass",
    "MAPOCA, compiled",
    "MAPOCA, MLP value",
    "MAPOCA, MLP critics",
    "MAPOCA, MLP critics, least-variance weight",
    "MAPPO",
)
""""MAPOCA" runs the estimation pass in its default pieces (``max_batch="auto"``), "MAPOCA,
one pass" on the whole batch at once (``max_batch=None``): the same results in more memory.
"MAPOCA, compiled" is the default with the README's ``torch.compile`` recipe (the critics'
networks and the loss); its first update, which compiles, is reported apart. "MAPOCA, MLP
value" has MAPPO's critic network as V (``mlp_value``) beside the default baselines, "MAPOCA,
MLP critics" that V and ``CounterfactualMLP`` baselines as wide and deep (2 x 128, tanh), and
"..., least-variance weight" the same with ``least_variance_weight=True``."""
DEFAULT_METHODS = ("MAPOCA", "MAPOCA, one pass", "MAPPO")


def make_actor() -> ProbabilisticActor:
    """One MLP shared by the agents, on each agent's observation: a tanh-Normal policy."""
    network = nn.Sequential(
        nn.Linear(OBSERVATION_DIM, 64),
        nn.Tanh(),
        nn.Linear(64, 64),
        nn.Tanh(),
        nn.Linear(64, 2 * ACTION_DIM),
        NormalParamExtractor(),
    )
    return ProbabilisticActor(
        TensorDictModule(
            network, in_keys=[OBSERVATION], out_keys=[(GROUP, "loc"), (GROUP, "scale")]
        ),
        in_keys=[(GROUP, "loc"), (GROUP, "scale")],
        out_keys=[ACTION],
        distribution_class=TanhNormal,  # on [-1, 1]
        return_log_prob=True,
    )


def make_loss(method: str, num_agents: int, args: argparse.Namespace) -> LossModule:
    actor = make_actor()
    estimator = {"gamma": 0.99, "lmbda": 0.95}
    if method.startswith("MAPOCA"):
        value = CentralValue(OBSERVATION_DIM, width=64, depth=1)
        baseline = CounterfactualBaseline(OBSERVATION_DIM, ACTION_DIM, width=64, depth=1)
        if method.startswith(("MAPOCA, MLP value", "MAPOCA, MLP critics")):
            value = mlp_value(num_agents, OBSERVATION_DIM, width=args.mlp_width, depth=2)
        if method.startswith("MAPOCA, MLP critics"):
            baseline = CounterfactualMLP(
                num_agents, OBSERVATION_DIM, ACTION_DIM, width=args.mlp_width, depth=2
            )
        loss = MAPOCALoss(
            actor, value, baseline, least_variance_weight=method.endswith("least-variance weight")
        )
    else:
        critic = TensorDictModule(
            MultiAgentMLP(
                n_agent_inputs=OBSERVATION_DIM,
                n_agent_outputs=1,
                n_agents=num_agents,
                centralized=True,
                share_params=True,
                depth=2,
                num_cells=args.mlp_width,
                activation_class=nn.Tanh,
            ),
            in_keys=[OBSERVATION],
            out_keys=[(GROUP, "state_value")],
        )
        loss = MAPPOLoss(actor, critic)
        loss.set_keys(value=(GROUP, "state_value"), reward=(GROUP, "reward"))
    if method == "MAPOCA, one pass":
        estimator["max_batch"] = None
    loss.make_value_estimator(loss.default_value_estimator, **estimator)
    if method == "MAPOCA, compiled":
        value.module.compile()
        baseline.module.compile()
        loss.compile()
    return loss


def make_batch(
    num_envs: int, steps: int, num_agents: int, device: torch.device, *, seed: int = 0
) -> TensorDict:
    """A collected batch [envs, steps] in VMAS's layout: per-agent observations and rewards,
    team done flags (every episode ends at the last step)."""
    generator = torch.Generator().manual_seed(seed)
    shape = (num_envs, steps)

    def normal(*size: int) -> torch.Tensor:
        return torch.randn(*shape, *size, generator=generator)

    done = torch.zeros(*shape, 1, dtype=torch.bool)
    done[:, -1] = True
    batch = TensorDict(
        {
            OBSERVATION: normal(num_agents, OBSERVATION_DIM),
            ("next", *OBSERVATION): normal(num_agents, OBSERVATION_DIM),
            ("next", GROUP, "reward"): normal(num_agents, 1),
            ("next", "done"): done,
            ("next", "terminated"): torch.zeros_like(done),
            ("next", GROUP, "done"): done.unsqueeze(-2).expand(*shape, num_agents, 1),
            ("next", GROUP, "terminated"): torch.zeros(*shape, num_agents, 1, dtype=torch.bool),
        },
        batch_size=shape,
    )
    return batch.to(device)


def estimate(loss: LossModule, batch: TensorDictBase) -> TensorDictBase:
    """The value-estimation pass as torchrl's MAPPO example calls it."""
    return loss.value_estimator(
        batch, params=loss.critic_network_params, target_params=loss.target_critic_network_params
    )


def update(
    loss: LossModule, optimiser: torch.optim.Optimizer, batch: TensorDictBase, minibatch: int
) -> None:
    """The value-estimation pass, then one epoch of mini-batches."""
    estimate(loss, batch)
    samples = batch.reshape(-1)
    for index in torch.randperm(samples.numel(), device=samples.device).split(minibatch):
        minibatch_step(loss, optimiser, samples[index])


def minibatch_step(
    loss: LossModule, optimiser: torch.optim.Optimizer, samples: TensorDictBase
) -> None:
    losses = loss(samples)
    total = sum(value for key, value in losses.items() if key.startswith("loss_"))
    optimiser.zero_grad()
    total.backward()
    optimiser.step()


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def _timed(
    function, device: torch.device, repeats: int, *, warmup: bool = True
) -> tuple[float, float]:
    """Median wall-clock and processor seconds of ``repeats`` calls (after one warm-up)."""
    if warmup:
        function()
    wall, processor = [], []
    for _ in range(repeats):
        _sync(device)
        start, start_processor = time.perf_counter(), time.process_time()
        function()
        _sync(device)
        wall.append(time.perf_counter() - start)
        processor.append(time.process_time() - start_processor)
    return statistics.median(wall), statistics.median(processor)


def _resident_kib(field: str) -> int:
    """``VmRSS`` (the resident set) or ``VmHWM`` (its peak) of this process, in KiB."""
    with open("/proc/self/status") as file:
        return next(int(line.split()[1]) for line in file if line.startswith(field + ":"))


def setup(
    method: str, num_agents: int, args: argparse.Namespace
) -> tuple[LossModule, torch.optim.Optimizer, TensorDict, torch.device]:
    """The loss, its optimiser and a collected batch, on ``args.device``."""
    torch.set_num_threads(args.threads)
    device = torch.device(args.device)
    torch.manual_seed(0)
    loss = make_loss(method, num_agents, args).to(device)
    optimiser = torch.optim.Adam(loss.parameters(), lr=1e-4)
    collected = make_batch(args.envs, args.steps, num_agents, device)
    with torch.no_grad():
        loss.actor_network(collected)  # collection: actions and their log-probs
    return loss, optimiser, collected, device


def peak_memory(method: str, num_agents: int, args: argparse.Namespace) -> float:
    """MiB that an update holds at most beyond what was there before it, after one warm-up
    update (which loads code and creates the optimiser's state)."""
    loss, optimiser, collected, device = setup(method, num_agents, args)
    update(loss, optimiser, collected.clone(), args.minibatch)
    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats(device)
        before = torch.cuda.memory_allocated(device)
        update(loss, optimiser, collected, args.minibatch)
        return (torch.cuda.max_memory_allocated(device) - before) / 2**20
    with open("/proc/self/clear_refs", "w") as file:
        file.write("5")  # the peak resident set restarts from the current one
    before = _resident_kib("VmRSS")
    update(loss, optimiser, collected, args.minibatch)
    return (_resident_kib("VmHWM") - before) / 2**10


def timing(method: str, num_agents: int, args: argparse.Namespace) -> dict:
    """Time per update (and of its parts)."""
    loss, optimiser, collected, device = setup(method, num_agents, args)
    first_wall, first_processor = _timed(
        lambda: update(loss, optimiser, collected.clone(), args.minibatch),
        device,
        repeats=1,
        warmup=False,
    )
    wall, processor = _timed(
        lambda: update(loss, optimiser, collected.clone(), args.minibatch), device, args.repeats
    )
    row = {
        "method": method,
        "agents": num_agents,
        "parameters": sum(p.numel() for p in loss.parameters()),
        "first_update_s": first_wall,
        "first_update_processor_s": first_processor,
        "update_s": wall,
        "update_processor_s": processor,
    }
    if args.parts:
        row["parts_ms"] = parts(loss, optimiser, collected, args, device)
    return row


def measure(method: str, num_agents: int, args: argparse.Namespace) -> dict:
    """:func:`timing`'s row with the :func:`peak_memory`, each in a fresh process: on CPU the
    peak is the process's. The memory's process has glibc return every block of 64 KiB or more
    to the system when freed (its threshold would otherwise rise with the first large frees),
    so that its resident set follows the live tensors; that costs time, so not the timing's."""
    context = get_context("spawn")
    with ProcessPoolExecutor(1, mp_context=context) as pool:
        row = pool.submit(timing, method, num_agents, args).result()
    os.environ["MALLOC_MMAP_THRESHOLD_"] = str(2**16)
    try:
        with ProcessPoolExecutor(1, mp_context=context) as pool:
            row["peak_memory_mb"] = pool.submit(peak_memory, method, num_agents, args).result()
    finally:
        del os.environ["MALLOC_MMAP_THRESHOLD_"]
    return row


def parts(
    loss: LossModule,
    optimiser: torch.optim.Optimizer,
    collected: TensorDictBase,
    args: argparse.Namespace,
    device: torch.device,
) -> dict[str, float]:
    """Milliseconds of the parts of one mini-batch step, each timed apart (forward and backward;
    "loss terms" is the step less the networks and the optimiser), and of the estimation pass
    (its critics on the collected steps and on the next steps, in its pieces; "returns" is the
    rest)."""
    batch = estimate(loss, collected.clone())
    samples = batch.reshape(-1)[: args.minibatch]

    def backward(output: torch.Tensor) -> None:
        output.float().sum().backward()

    def actor() -> None:
        dist = loss.actor_network.get_dist(samples.copy())
        backward(dist.log_prob(samples[ACTION]) + dist.log_prob(dist.rsample()))

    timed = {
        "step": lambda: minibatch_step(loss, optimiser, samples.copy()),
        "actor": actor,
        "optimiser": optimiser.step,
    }
    if isinstance(loss, MAPOCALoss):
        value, baseline = loss.value_network.module, loss.baseline_network.module
        observation = samples[OBSERVATION]
        pair = torch.cat([observation, samples[ACTION]], -1)
        timed["value network"] = lambda: backward(value(observation))
        if isinstance(baseline, AttentionBaseline):
            timed["baseline encoders"] = lambda: backward(
                baseline.own_state(observation) + baseline.other_state_action(pair)
            )
        timed["baseline network"] = lambda: backward(baseline(observation, samples[ACTION]))
    else:
        timed["critic"] = lambda: backward(
            loss.critic_network(samples.copy())[loss.tensor_keys.value]
        )

    def milliseconds(function) -> float:
        wall, processor = _timed(function, device, args.repeats)
        return 1e3 * (processor if device.type == "cpu" else wall)

    ms = {name: milliseconds(function) for name, function in timed.items()}
    networks = sum(
        ms[name] for name in ("actor", "value network", "baseline network", "critic") if name in ms
    )
    ms["loss terms"] = ms["step"] - networks - ms["optimiser"]
    if "baseline encoders" in ms:
        ms["baseline attention and head"] = ms["baseline network"] - ms["baseline encoders"]

    root, next_step = collected.exclude("next"), collected["next"]
    with torch.no_grad():
        ms["estimation"] = milliseconds(lambda: estimate(loss, collected.clone()))
        if isinstance(loss, MAPOCALoss):
            # in the pieces the estimation pass runs them in
            estimator = loss.value_estimator
            elements = estimator._piece_elements(root)
            ms["estimation: critics (collected)"] = milliseconds(
                lambda: estimator._critics(root.copy(), with_baseline=True, elements=elements)
            )
            ms["estimation: critics (next)"] = milliseconds(
                lambda: estimator._critics(next_step.copy(), with_baseline=False, elements=elements)
            )
        else:
            ms["estimation: critics (collected)"] = milliseconds(
                lambda: loss.critic_network(root.copy())
            )
            ms["estimation: critics (next)"] = milliseconds(
                lambda: loss.critic_network(next_step.copy())
            )
        ms["estimation: returns"] = (
            ms["estimation"]
            - ms["estimation: critics (collected)"]
            - ms["estimation: critics (next)"]
        )
    return ms


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--agents", type=int, nargs="+", default=[4, 16])
    parser.add_argument("--methods", nargs="+", default=list(DEFAULT_METHODS), choices=METHODS)
    parser.add_argument("--envs", type=int, default=60)
    parser.add_argument("--steps", type=int, default=100)
    parser.add_argument("--minibatch", type=int, default=400)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument(
        "--mlp-width", type=int, default=128, help="hidden width of MAPPO's and the MLP critics"
    )
    parser.add_argument("--threads", type=int, default=1, help="torch CPU threads")
    parser.add_argument("--parts", action="store_true", help="also time the parts of an update")
    parser.add_argument("--out", type=Path, default=None, help="JSON path (default by device)")
    args = parser.parse_args()
    device = torch.device(args.device)
    out = args.out or Path(__file__).parent / "results" / f"loss_speed_{device.type}.json"
    results = {
        "date": date.today().isoformat(),
        "device": device_name(device),
        "threads": args.threads if device.type == "cpu" else None,
        "settings": {
            key: getattr(args, key)
            for key in ("envs", "steps", "minibatch", "repeats", "mlp_width")
        },
        "rows": [],
    }
    print(
        f"{results['device']}, {args.envs} x {args.steps} frames, mini-batches of {args.minibatch}"
    )
    header = ("K", "method", "params", "first s", "wall s", "cpu s", "peak MB", "time x", "mem x")
    print("{:>3s} {:16s} {:>7s} {:>8s} {:>8s} {:>8s} {:>8s} {:>7s} {:>6s}".format(*header))
    # on a CPU shared with other work, the processor time the update took is the steadier
    clock = "update_processor_s" if device.type == "cpu" else "update_s"
    results["time_ratio_of"] = clock
    for num_agents in args.agents:
        rows = {}
        for method in ("MAPPO", *(m for m in args.methods if m != "MAPPO")):  # MAPPO: the ratios'
            rows[method] = measure(method, num_agents, args)
        for method in args.methods:
            row = rows[method]
            row["time_ratio"] = row[clock] / rows["MAPPO"][clock]
            row["memory_ratio"] = row["peak_memory_mb"] / rows["MAPPO"]["peak_memory_mb"]
            results["rows"].append(row)
            print(
                f"{num_agents:3d} {method:16s} {row['parameters']:7d} "
                f"{row['first_update_s']:8.3f} {row['update_s']:8.3f} "
                f"{row['update_processor_s']:8.3f} {row['peak_memory_mb']:8.1f} "
                f"{row['time_ratio']:7.2f} {row['memory_ratio']:6.2f}"
            )
        write_results(out, results)
        if args.parts:
            for method in args.methods:
                print(f"  K = {num_agents} {method} parts (ms):")
                for name, ms in rows[method]["parts_ms"].items():
                    print(f"    {name:34s} {ms:8.2f}")
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
