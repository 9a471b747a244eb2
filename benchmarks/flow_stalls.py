"""Why the sliding families' spheres stop: their scripted heuristic with and without steering clear.

On a flat top, friction leaves C = v + (2/5) r (w x z) of a sphere as it was, and a sphere
rolling on a surface sliding at u moves at (2u + 5C)/7 (docs/physics.md): a steady flow exerts
no force on it. A sphere that the flow presses against another spins up until it rolls in place
(C = -2u/5), and then only a flow faster than u moves it further that way; the rotors' surface
slides too. This script plays the pretraining scene of ``--actuator`` (``surface_flow`` unless
told; box columns, evaluation mode, the main job's ``shape`` actions unless ``--action-mode``) with
:class:`~terrashift_rl.envs.baselines.ScriptedHeuristicPolicy` at each ``--clearances`` value
("none": every sphere driven straight at its goal) and reports, per value over the seeds:

- the goal fraction, the mean episode length [decisions], the share of episodes cut by the step
  limit, the spheres lost out of bounds per episode and the surface's work per goal [J];
- ``rolling_in_place``: of the spheres still in play when their episode hit the step limit, the
  share that rolled in place there (slower than 0.03 m/s with |C| above 0.3 m/s);
- ``spun_up`` and ``spun_up_after_contact``: the spheres per episode whose |C| passed 0.2 m/s,
  and how many of them had touched another sphere before.

``--overrides`` changes the scene (``TerraShiftConfig`` fields). Prints a table and writes JSON.

    python benchmarks/flow_stalls.py --num-envs 64 --seeds 0 1 2
    python benchmarks/flow_stalls.py --clearances none --overrides num_objects=1 num_goals=1
    python benchmarks/flow_stalls.py --actuator rotors --num-envs 64 --seeds 0 1 2
"""

from __future__ import annotations

import statistics
from pathlib import Path

import torch
from common import (
    benchmark_parser,
    field_parser,
    run_header,
    table_header,
    table_row,
    write_results,
)

from terrashift_rl.envs import TerraShiftEnv
from terrashift_rl.envs.baselines import ScriptedHeuristicPolicy
from terrashift_rl.sim import Simulator, TerraShiftConfig
from terrashift_rl.sim.config import ACTION_MODES
from terrashift_rl.training.evaluation import evaluation_scene

SPUN_UP = 0.2
"""|C| [m/s] past which a sphere counts as spun up: on a 1 m/s flow it then moves along the
flow at most at (2 - 5 * 0.2) / 7 = 0.14 m/s, half its speed from rest."""


def stored_spin(sim: Simulator) -> torch.Tensor:
    """C = v + (2/5) r (w x z) of every sphere, [num_envs, M, 2] [m/s]."""
    r = sim.config.sphere_radius
    v = sim.view("sphere_velocity")[..., :2]
    w = sim.view("sphere_angular_velocity")
    return v + 0.4 * r * torch.stack([w[..., 1], -w[..., 0]], dim=-1)


def play(config: TerraShiftConfig, clearance: float | None, num_envs: int, seed: int) -> dict:
    """One evaluation episode per environment; the metrics of the module's docstring."""
    env = TerraShiftEnv(config, num_envs=num_envs, seed=seed)
    policy = ScriptedHeuristicPolicy(config, clearance=clearance)
    sim, m = env.sim, config.num_objects
    running = torch.ones(num_envs, dtype=torch.bool)
    touched = torch.zeros(num_envs, m, dtype=torch.bool)
    spun = torch.zeros(num_envs, m, dtype=torch.bool)
    was_active = torch.zeros(num_envs, m, dtype=torch.bool)
    totals = dict.fromkeys(("length", "goals", "lost", "work", "truncated", "spun_up"), 0.0)
    totals.update(spun_up_after_contact=0.0, left=0.0, rolling_in_place=0.0)
    others = ~torch.eye(m, dtype=torch.bool)
    in_place = torch.zeros(num_envs, m, dtype=torch.bool)
    td = env.reset()
    with torch.no_grad():
        for _ in range(config.max_episode_steps):
            out, td = env.step_and_maybe_reset(policy(td))
            nxt = out["next"]
            done = nxt["done"].reshape(num_envs) & running
            truncated = done & nxt["truncated"].reshape(num_envs)
            totals["length"] += float(running.sum())
            totals["truncated"] += float(truncated.sum())
            for name, key in (
                ("goals", "episode_goals"),
                ("lost", "episode_out_of_bounds"),
                ("work", "episode_surface_work"),
            ):
                totals[name] += float(nxt[key].reshape(num_envs)[done].sum())
            # a finished environment is reset within the step, so the spheres left at the step
            # limit are read as they were one decision before
            left = was_active & truncated.unsqueeze(-1)
            totals["left"] += float(left.sum())
            totals["rolling_in_place"] += float((left & in_place).sum())
            running &= ~done
            active = sim.view("sphere_active").bool() & running.unsqueeze(-1)
            new = active & ~was_active
            touched &= ~new
            spun &= ~new
            position = sim.view("sphere_position")
            gap = (position.unsqueeze(2) - position.unsqueeze(1)).norm(dim=-1)
            near = (gap < 2 * config.sphere_radius + 2e-3) & active.unsqueeze(1) & others
            touched |= near.any(-1) & active
            spin = stored_spin(sim).norm(dim=-1)
            first = (spin > SPUN_UP) & active & ~spun
            totals["spun_up"] += float(first.sum())
            totals["spun_up_after_contact"] += float((first & touched).sum())
            spun |= first
            speed = sim.view("sphere_velocity")[..., :2].norm(dim=-1)
            in_place = (speed < 0.03) & (spin > 0.3)
            was_active = active
            if not running.any():
                break
    episodes = float(num_envs)
    return {
        "goal_fraction": totals["goals"] / (episodes * m),
        "mean_episode_length": totals["length"] / episodes,
        "truncated_fraction": totals["truncated"] / episodes,
        "out_of_bounds_per_episode": totals["lost"] / episodes,
        "surface_work_per_goal": totals["work"] / max(totals["goals"], 1.0),
        "rolling_in_place": totals["rolling_in_place"] / max(totals["left"], 1.0),
        "spun_up": totals["spun_up"] / episodes,
        "spun_up_after_contact": totals["spun_up_after_contact"] / episodes,
    }


def main() -> None:
    parser = benchmark_parser(__doc__)
    parser.add_argument("--num-envs", type=int, default=64, help="episodes per seed")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--clearances", nargs="+", default=["none", "2.0"])
    parser.add_argument("--actuator", default="surface_flow", choices=("surface_flow", "rotors"))
    parser.add_argument("--action-mode", default="shape", choices=ACTION_MODES)
    parser.add_argument(
        "--overrides",
        type=field_parser(TerraShiftConfig),
        nargs="+",
        default=[],
        metavar="FIELD=VALUE",
    )
    parser.add_argument("--out", type=Path, default=None, help="JSON path")
    args = parser.parse_args()
    overrides = dict(args.overrides)
    name = "flow_stalls_cpu" + ("" if args.actuator == "surface_flow" else f"_{args.actuator}")
    out = args.out or Path(__file__).parent / "results" / f"{name}.json"
    config = evaluation_scene(
        TerraShiftConfig.preset(
            "pretrain",
            actuator=args.actuator,
            column_shape="box",
            action_mode=args.action_mode,
            count_surface_work=True,
            **overrides,
        )
    )
    payload = {
        "benchmark": "flow_stalls",
        **run_header(torch.device("cpu")),
        "scene": f"pretrain, {args.actuator}, box columns, {args.action_mode} actions, no respawn",
        "overrides": overrides,
        "episodes_per_seed": args.num_envs,
        "seeds": args.seeds,
        "rows": [],
    }
    names = ["goal_fraction", "mean_episode_length", "truncated_fraction",
             "out_of_bounds_per_episode", "surface_work_per_goal", "rolling_in_place",
             "spun_up", "spun_up_after_contact"]  # fmt: skip
    print(table_header(["clearance", *names]))
    for value in args.clearances:
        clearance = None if value == "none" else float(value)
        per_seed = [play(config, clearance, args.num_envs, seed) for seed in args.seeds]
        row = {"clearance": clearance}
        for name in names:
            row[name] = statistics.fmean(scores[name] for scores in per_seed)
        fractions = [scores["goal_fraction"] for scores in per_seed]
        row["goal_fraction_sd"] = statistics.stdev(fractions) if len(fractions) > 1 else 0.0
        payload["rows"].append(row)
        write_results(out, payload)
        print(table_row([value, *(f"{row[name]:.3f}" for name in names)]))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
