"""Where a policy's evaluation episodes spend their decisions: how soon its spheres reach their
goals, and where the spheres still in play at the step limit sit.

    python benchmarks/endgame.py <run dir>/checkpoints/last.pt ... --heuristic

Per checkpoint (``last.pt`` or ``best.pt`` of a recipe run), on its scene in evaluation mode
(:func:`~terrashift_rl.training.evaluation.evaluation_scene`: no respawn; the Beta mean), one
episode in each of ``--envs`` environments of seed ``--seed``'s scenes, as the periodic
evaluation plays them:

- **Pace.** The goal fraction reached by decisions 100, 200, 300, 400 and the step limit, and
  the decisions from a sphere's spawn to its goal (median and 90th percentile).
- **Unresolved.** The share of spheres neither at their goal nor lost when the episode ends at
  the step limit; for those, at the end: their distance to their goal and how much it fell over
  the last 100 decisions, their mean speed over those decisions (to compare with the slow
  penalty's ``slow_speed``), the distance to the nearest wavelet centre [cells], the height of
  the column under them (``-max_column_height`` at the bottom of the deepest basin), and the
  share of them that no wavelet has as its nearest sphere (left alone) or that every wavelet
  has (the whole team on one sphere).
- **Wavelets.** The share of wavelet-decisions with a negative amplitude (a basin rather than a
  bump) and at the amplitude's lower limit.

``--heuristic`` adds the scripted heuristic on the first checkpoint's scene. Prints a table and
writes JSON.
"""

from __future__ import annotations

import argparse
from collections.abc import Callable
from datetime import date
from pathlib import Path

import torch
from common import device_name, write_results
from diagnose_policy import nearest_wavelet_cells, resolution_kind, wavelet_cells
from tensordict import TensorDictBase
from torchrl.envs import EnvBase
from torchrl.envs.utils import ExplorationType, step_mdp

from terrashift_rl.envs import TerraShiftEnv
from terrashift_rl.envs.baselines import ScriptedHeuristicPolicy
from terrashift_rl.modules import TerraShiftModelConfig, make_terrashift_networks
from terrashift_rl.sim import TerraShiftConfig
from terrashift_rl.training import load_checkpoint, make_training_env
from terrashift_rl.training.evaluation import actor_policy, evaluation_scene

MILESTONES = (100, 200, 300, 400)
"""Decisions at which the goal fraction reached so far is reported (and at the step limit)."""

LOOK_BACK = 100
"""Decisions over which an unresolved sphere's progress towards its goal is measured."""


def column_under(sim, scene: TerraShiftConfig) -> torch.Tensor:
    """Height [m] of the column under every sphere's centre, [E, M]."""
    cell = (sim.view("sphere_position")[..., :2] + 0.5 * scene.platform_size) / scene.cell_size
    cell = cell.long().clamp(0, scene.grid_size - 1)
    height = sim.view("column_height")  # [E, G (y), G (x)]
    env = torch.arange(height.shape[0], device=height.device).unsqueeze(1)
    return height[env, cell[..., 1], cell[..., 0]]


def wavelets_nearest_to(sim, scene: TerraShiftConfig) -> torch.Tensor:
    """How many wavelets have each sphere as their nearest active sphere, [E, M] (0 for the
    inactive ones)."""
    active = sim.view("sphere_active") == 1
    distance = wavelet_cells(sim, scene).masked_fill(~active.unsqueeze(-1), float("inf"))
    nearest = distance.argmin(1)  # [E, K]: each wavelet's nearest active sphere
    counts = torch.nn.functional.one_hot(nearest, active.shape[1]).sum(1)
    return torch.where(active, counts, 0)


def _median(values: torch.Tensor) -> float | None:
    return values.float().median().item() if values.numel() else None


def _share(flags: torch.Tensor) -> float | None:
    return flags.float().mean().item() if flags.numel() else None


@torch.no_grad()
def endgame(
    env: EnvBase,
    sim,
    policy: Callable[[TensorDictBase], TensorDictBase],
    scene: TerraShiftConfig,
) -> dict:
    """Plays one evaluation episode in every environment of ``env`` (whose simulator is
    ``sim``, on ``scene`` without respawn) with ``policy`` and measures its pace, its unresolved
    spheres and its wavelets' amplitudes (module docstring)."""
    if scene.respawn:
        raise ValueError("endgame needs a scene in evaluation mode (respawn=False)")
    num_envs, num_objects = sim.view("sphere_active").shape
    device = sim.view("sphere_active").device
    spawned_at = torch.full((num_envs, num_objects), -1, device=device)
    resolved_at = torch.full((num_envs, num_objects), -1, device=device)
    at_goal = torch.zeros(num_envs, num_objects, dtype=torch.bool, device=device)
    running = torch.ones(num_envs, dtype=torch.bool, device=device)
    distances, speeds = [], []  # goal distance and planar speed [E, M] before each decision
    negative, at_floor, wavelet_decisions = 0, 0, 0
    floor = scene.min_amplitude_ratio * scene.max_amplitude
    td = env.reset()
    for t in range(scene.max_episode_steps):
        active = sim.view("sphere_active") == 1
        spawned_at = torch.where((spawned_at < 0) & active, t, spawned_at)
        distances.append(sim.view("goal_distance").clone())
        speeds.append(sim.view("sphere_velocity")[..., :2].norm(dim=-1))
        amplitude = sim.view("agent_amplitude")[running]
        negative += int((amplitude < 0).sum())
        at_floor += int((amplitude <= floor + 1e-6 * scene.max_amplitude).sum())
        wavelet_decisions += amplitude.numel()
        td = step_mdp(env.step(policy(td)))
        resolved = active & (sim.view("sphere_active") == 0) & running.unsqueeze(1)
        position = sim.view("sphere_position")
        for e, j in resolved.nonzero().tolist():
            resolved_at[e, j] = t
            at_goal[e, j] = resolution_kind(position[e, j], scene) == "goal"
        running &= ~td.get("done").reshape(num_envs)
        if not running.any():
            break
    unresolved = (resolved_at < 0) & (spawned_at >= 0)
    spheres = num_envs * num_objects
    reached = {
        str(m): float(((resolved_at >= 0) & (resolved_at < m) & at_goal).sum()) / spheres
        for m in MILESTONES
    }
    reached[str(scene.max_episode_steps)] = float(at_goal.sum()) / spheres
    to_goal = (resolved_at - spawned_at + 1)[at_goal]
    end = distances[-1][unresolved]
    before = distances[max(0, len(distances) - 1 - LOOK_BACK)][unresolved]
    speed = torch.stack(speeds[-LOOK_BACK:]).mean(0)[unresolved]
    claims = wavelets_nearest_to(sim, scene)
    return {
        "goal_fraction_by_decision": reached,
        "decisions_to_goal_median": _median(to_goal),
        "decisions_to_goal_p90": (
            to_goal.float().quantile(0.9).item() if to_goal.numel() else None
        ),
        "lost_fraction": float(((resolved_at >= 0) & ~at_goal).sum()) / spheres,
        "unresolved_fraction": float(unresolved.sum()) / spheres,
        "unresolved_goal_distance_m": _median(end),
        "unresolved_goal_distance_fall_m": _median(before - end),
        "unresolved_mean_speed_m_per_s": _median(speed),
        "unresolved_nearest_wavelet_cells": _median(nearest_wavelet_cells(sim, scene)[unresolved]),
        "unresolved_column_height_m": _median(column_under(sim, scene)[unresolved]),
        "unresolved_share_left_alone": _share(claims[unresolved] == 0),
        "unresolved_share_with_every_wavelet": _share(claims[unresolved] == scene.num_agents),
        "share_negative_amplitude": negative / max(wavelet_decisions, 1),
        "share_at_amplitude_floor": at_floor / max(wavelet_decisions, 1),
    }


def checkpoint_row(
    path: Path, args: argparse.Namespace, device: torch.device
) -> tuple[dict, TerraShiftConfig]:
    """The row of a checkpoint, and the scene it was trained on."""
    checkpoint = load_checkpoint(path, map_location=device)
    trained_on = TerraShiftConfig(**checkpoint["env_config"])
    scene = evaluation_scene(trained_on)
    networks = make_terrashift_networks(TerraShiftModelConfig(**checkpoint["model_config"]))
    networks.load_state_dict(checkpoint["networks"])
    networks.to(device).eval()
    env = make_training_env(scene, networks, num_envs=args.envs, device=device, seed=args.seed)
    policy = actor_policy(networks.actor, ExplorationType.DETERMINISTIC)
    row = {
        "checkpoint": str(path),
        "env_steps": checkpoint["env_steps"],
        **endgame(env, env.base_env.sim, policy, scene),
    }
    return row, trained_on


def heuristic_row(scene: TerraShiftConfig, args: argparse.Namespace, device) -> dict:
    scene = evaluation_scene(scene)
    env = TerraShiftEnv(scene, num_envs=args.envs, device=device, seed=args.seed)
    return {
        "checkpoint": "scripted heuristic",
        "env_steps": None,
        **endgame(env, env.sim, ScriptedHeuristicPolicy(scene), scene),
    }


def format_row(row: dict) -> str:
    def number(value, digits=2, scale=1.0):
        return "" if value is None else f"{scale * value:.{digits}f}"

    reached = ", ".join(f"{v:.2f}" for v in row["goal_fraction_by_decision"].values())
    cells = [
        row["checkpoint"],
        "" if row["env_steps"] is None else f"{row['env_steps'] / 1e6:.1f} M",
        reached,
        f"{number(row['decisions_to_goal_median'], 0)}, {number(row['decisions_to_goal_p90'], 0)}",
        f"{row['lost_fraction']:.2f}, {row['unresolved_fraction']:.2f}",
        f"{number(row['unresolved_goal_distance_m'])}, "
        f"{number(row['unresolved_goal_distance_fall_m'], 3)}, "
        f"{number(row['unresolved_mean_speed_m_per_s'])}, "
        f"{number(row['unresolved_nearest_wavelet_cells'], 1)}, "
        f"{number(row['unresolved_column_height_m'], 0, 1000.0)}",
        f"{number(row['unresolved_share_left_alone'])}, "
        f"{number(row['unresolved_share_with_every_wavelet'])}",
        f"{row['share_negative_amplitude']:.2f}, {row['share_at_amplitude_floor']:.2f}",
    ]
    return "| " + " | ".join(cells) + " |"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("checkpoints", nargs="*", type=Path, help="last.pt or best.pt files")
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    parser.add_argument("--envs", type=int, default=128, help="episodes per policy")
    parser.add_argument("--seed", type=int, default=1, help="the scenes (evaluation's: 1)")
    parser.add_argument(
        "--heuristic",
        action="store_true",
        help="add the scripted heuristic on the first checkpoint's scene (the default scene "
        "without checkpoints)",
    )
    parser.add_argument(
        "--out", type=Path, default=Path(__file__).parent / "results" / "endgame.json"
    )
    args = parser.parse_args()
    if args.envs < 1:
        parser.error(f"--envs must be at least 1, got {args.envs}")
    if not args.checkpoints and not args.heuristic:
        parser.error("name at least one checkpoint, or --heuristic")
    for path in args.checkpoints:
        if not path.is_file():
            parser.error(f"no checkpoint at {path}")
    device = torch.device(args.device)
    payload = {
        "date": date.today().isoformat(),
        "device": device_name(device),
        "envs": args.envs,
        "seed": args.seed,
        "rows": [],
    }
    print(
        f"Evaluation episodes: {args.envs} per policy, seed {args.seed}'s scenes, "
        f"{payload['device']}"
    )
    print(
        f"| policy | env-steps | goal fraction by decision {', '.join(map(str, MILESTONES))}, "
        "the limit | decisions to goal: median, 90th percentile | lost, unresolved "
        f"| unresolved: goal distance [m], its fall over the last {LOOK_BACK} decisions [m], "
        "mean speed over them [m/s], nearest wavelet [cells], column under it [mm] "
        "| unresolved: no wavelet's nearest sphere, every wavelet's "
        "| wavelet-decisions: negative amplitude, at the floor |"
    )
    print("|---|---:|---|---|---|---|---|---|")

    def record(row: dict) -> None:
        payload["rows"].append(row)
        print(format_row(row), flush=True)
        write_results(args.out, payload)

    first_scene = None
    for path in args.checkpoints:
        row, scene = checkpoint_row(path, args, device)
        first_scene = first_scene or scene
        record(row)
    if args.heuristic:
        record(heuristic_row(first_scene or TerraShiftConfig(), args, device))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
