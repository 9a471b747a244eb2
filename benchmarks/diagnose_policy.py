"""What a trained policy does: where its spheres go, how its wavelets move, and how much of the
PPO ratio's spread in an update comes from dropout alone.

    python benchmarks/diagnose_policy.py <run dir>/checkpoints/best.pt <run dir>/checkpoints/last.pt

Per checkpoint (``last.pt`` or ``best.pt`` of a recipe run), on the scene it was trained on:

- **Resolutions.** The policy (sampled actions) drives ``--envs`` environments in training mode
  (respawn on) for ``--decisions`` decisions. A resolved sphere keeps the position at which it
  resolved, so each is classed by it: at its goal, past the platform's side (``|x|`` or ``|y|``
  above ``out_of_bounds_xy``), thrown above ``out_of_bounds_z``, or below the platform. For the
  spheres lost past the side: their distance to their goal one decision before.
- **Spheres.** Over the same decisions, of the spheres in play: the share served (a wavelet
  centre within ``--serve-radius`` cells; the scripted heuristic stands 2 cells behind its
  sphere), the median distance to the nearest wavelet, the share at rest (slower than the
  scene's ``slow_speed``, the speed below which the reward's slow penalty applies), and how
  far they come nearer their goals per decision on average.
- **Wavelets and policy.** Over the same decisions: the share of wavelet-decisions at the speed
  limit (either axis) and at the amplitude limit, the mean width, and per action dimension the
  median Beta concentration alpha + beta (large: a nearly deterministic dimension).
- **PPO ratio at zero updates.** One batch collected as the trainer collects it (dropout off),
  then the loss on it exactly as an update computes it, before any gradient step: with the
  update's dropout on, the approximate KL and the clip fraction at clip ranges 0.2 and 0.1. With
  dropout off both are zero, so what this shows is the spread that dropout alone adds to every
  update's ratios (and to the logged ``kl_approx`` and ``clip_fraction``).
- **Counterfactual baselines.** On the same batch, relative to the baselines' spread over it:
  how far the baselines b_i of one step's agents lie apart (the only per-agent part of the
  advantages G - b_i), and how much they move when every action is sampled again from the
  policy (their dependence on the other agents' actions). With both near zero, the agents of a
  step share one advantage.

``--heuristic`` adds the scripted heuristic's rollout statistics on the first checkpoint's
scene, for reference. Prints a table and writes JSON.
"""

from __future__ import annotations

import argparse
import statistics
from datetime import date
from pathlib import Path

import torch
from common import device_name, write_results
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.modules import set_recurrent_mode

from terrashift_rl.envs import TerraShiftEnv
from terrashift_rl.envs.baselines import ScriptedHeuristicPolicy
from terrashift_rl.modules import TerraShiftModelConfig, keys, make_terrashift_networks
from terrashift_rl.sim import TerraShiftConfig
from terrashift_rl.sim.types import ACTION_NAMES
from terrashift_rl.training import (
    MAPOCATrainer,
    TrainConfig,
    concentration_metrics,
    load_checkpoint,
    make_training_env,
)

KINDS = ("goal", "past the side", "thrown above", "below the platform")


def resolution_kind(position: torch.Tensor, scene: TerraShiftConfig) -> str:
    """Where a sphere that resolved at ``position`` [3] did so."""
    if position[2] > scene.out_of_bounds_z:
        return "thrown above"
    if position[2] < 0.0:
        return "below the platform"
    if position[:2].abs().max() > scene.out_of_bounds_xy:
        return "past the side"
    return "goal"


def wavelet_cells(sim, scene: TerraShiftConfig) -> torch.Tensor:
    """Distance [cells] from every sphere to every wavelet centre, [E, M, K]; on a grid that
    wraps, the wavelets' positions wrap too."""
    half = 0.5 * scene.platform_size
    sphere = (sim.view("sphere_position")[..., :2] + half) / scene.cell_size - 0.5
    offset = (sim.view("agent_position").unsqueeze(1) - sphere.unsqueeze(2)).abs()
    if scene.wrap_edges:
        offset = torch.minimum(offset, scene.grid_size - offset)  # [E, M, K, 2]
    return offset.norm(dim=-1)


def nearest_wavelet_cells(sim, scene: TerraShiftConfig) -> torch.Tensor:
    """Distance [cells] from every sphere to the nearest wavelet centre, [E, M]."""
    return wavelet_cells(sim, scene).amin(-1)


@torch.no_grad()
def rollout(env, sim, act, scene: TerraShiftConfig, args: argparse.Namespace) -> dict:
    """Resolutions, sphere, wavelet and concentration statistics of the policy ``act``
    (sampled actions) in ``env``, whose simulator is ``sim``; concentrations only where
    ``act`` writes Beta parameters."""
    counts = dict.fromkeys(KINDS, 0)
    side_distance = []
    at_speed_limit, at_amplitude_limit, width, policy = [], [], [], []
    served, at_rest, approach, nearest = [], [], [], []
    td = env.reset()
    with set_exploration_type(ExplorationType.RANDOM):
        for _ in range(args.decisions):
            was_active = sim.view("sphere_active") == 1
            distance = sim.view("goal_distance").clone()
            wavelet_distance = nearest_wavelet_cells(sim, scene)[was_active]
            served.append((wavelet_distance <= args.serve_radius).float().mean())
            nearest.append(wavelet_distance)
            speed = sim.view("sphere_velocity")[..., :2].norm(dim=-1)[was_active]
            at_rest.append((speed < scene.slow_speed).float().mean())
            td = act(td)
            if keys.BETA_CONCENTRATION0 in td.keys(include_nested=True):
                concentration = (keys.BETA_CONCENTRATION0, keys.BETA_CONCENTRATION1)
                policy.append(td.select(*concentration).clone())
            _, td = env.step_and_maybe_reset(td)
            is_active = sim.view("sphere_active") == 1
            approach.append((distance - sim.view("goal_distance"))[was_active & is_active].mean())
            position = sim.view("sphere_position")
            for e, j in (was_active & ~is_active).nonzero().tolist():
                kind = resolution_kind(position[e, j], scene)
                counts[kind] += 1
                if kind == "past the side":
                    side_distance.append(distance[e, j].item())
            wavelet_speed = sim.view("agent_velocity").abs().amax(-1)
            at_speed_limit.append((wavelet_speed >= 0.99 * scene.max_velocity).float().mean())
            amplitude = sim.view("agent_amplitude").abs()
            at_amplitude_limit.append((amplitude >= 0.99 * scene.max_amplitude).float().mean())
            width.append(sim.view("agent_sigma").mean())
    resolved = sum(counts.values())
    return {
        "resolutions": counts,
        "success_rate": counts["goal"] / resolved if resolved else 0.0,
        "median_goal_distance_before_past_the_side": (
            statistics.median(side_distance) if side_distance else None
        ),
        "share_of_spheres_served": torch.stack(served).nanmean().item(),
        "median_nearest_wavelet_cells": torch.cat(nearest).median().item(),
        "share_of_spheres_at_rest": torch.stack(at_rest).nanmean().item(),
        "mean_approach_per_decision_m": torch.stack(approach).nanmean().item(),
        "share_at_speed_limit": torch.stack(at_speed_limit).mean().item(),
        "share_at_amplitude_limit": torch.stack(at_amplitude_limit).mean().item(),
        "mean_width_cells": torch.stack(width).mean().item(),
        "median_concentration_per_dim": (
            list(concentration_metrics(torch.stack(policy)).values()) if policy else None
        ),
    }


def collected_batch(networks, scene: TerraShiftConfig, args, device):
    """A trainer and one batch it collected (dropout off), with its value-estimation pass."""
    env = make_training_env(scene, networks, num_envs=args.envs, device=device, seed=args.seed)
    trainer = MAPOCATrainer(
        env, networks, TrainConfig(num_envs=args.envs, minibatches=1, cuda_graphs=False)
    )
    trainer.collect()  # the second batch starts in the middle of episodes
    data = trainer.collect()
    networks.eval()
    trainer.loss.value_estimator(data)
    return trainer, data


def ratio_at_zero_updates(trainer: MAPOCATrainer, data) -> dict:
    """Approximate KL and clip fractions of a first update's ratios, dropout on."""
    networks = trainer.networks
    networks.train()  # dropout acts in train mode in passes autograd records, as in an update
    result = {}
    for clip in (0.2, 0.1):
        trainer.loss.clip_epsilon.fill_(clip)
        with set_recurrent_mode(True):
            out = trainer.loss(data)
        result[f"clip_fraction_{clip}"] = out["clip_fraction"].item()
        result["kl_approx"] = out["kl_approx"].item()
    networks.eval()
    return result


@torch.no_grad()
def baseline_credit(trainer: MAPOCATrainer, data) -> dict:
    """How much the counterfactual baselines b_i tell the agents of one step apart, and how
    much they depend on the other agents' actions, both relative to b's spread over the batch.

    ``agent_spread``: the mean over steps of b_i's standard deviation across agents, the only
    part of the advantages G - b_i that differs between the agents of a step. ``action_effect``:
    the mean |b_i(s, a'_-i) - b_i(s, a_-i)| when every action is sampled again from the policy.
    """
    baseline = data.get(keys.BASELINE).squeeze(-1)  # [N, T, K], as the critic outputs it
    with set_exploration_type(ExplorationType.RANDOM), set_recurrent_mode(False):
        resampled = trainer.networks.actor(data.exclude("next").clone()).get(keys.ACTION)
    other = data.clone()
    other.set(keys.ACTION, resampled)
    trainer.loss.value_estimator(other)
    changed = other.get(keys.BASELINE).squeeze(-1)
    scale = baseline.std()
    return {
        "agent_spread": (baseline.std(-1).mean() / scale).item(),
        "action_effect": ((changed - baseline).abs().mean() / scale).item(),
    }


def diagnose(path: Path, args: argparse.Namespace, device: torch.device) -> dict:
    checkpoint = load_checkpoint(path, map_location=device)
    scene = TerraShiftConfig(**checkpoint["env_config"])
    model = TerraShiftModelConfig(**checkpoint["model_config"])
    networks = make_terrashift_networks(model).to(device)
    networks.load_state_dict(checkpoint["networks"])
    torch.manual_seed(args.seed)
    env = make_training_env(scene, networks, num_envs=args.envs, device=device, seed=args.seed)
    networks.eval()
    rollout_statistics = rollout(env, env.base_env.sim, networks.actor, scene, args)
    trainer, data = collected_batch(networks, scene, args, device)
    return {
        "checkpoint": str(path),
        "iteration": checkpoint["iteration"],
        "env_steps": checkpoint["env_steps"],
        "dropout": model.dropout,
        **rollout_statistics,
        "ratio_at_zero_updates": ratio_at_zero_updates(trainer, data),
        "baseline": baseline_credit(trainer, data),
    }


def diagnose_heuristic(scene: TerraShiftConfig, args: argparse.Namespace, device) -> dict:
    """The rollout statistics of the scripted heuristic on ``scene``, for reference."""
    env = TerraShiftEnv(scene, num_envs=args.envs, device=device, seed=args.seed)
    return {
        "checkpoint": "scripted heuristic",
        "iteration": None,
        "env_steps": None,
        **rollout(env, env.sim, ScriptedHeuristicPolicy(scene), scene, args),
    }


def format_row(row: dict) -> str:
    counts = row["resolutions"]
    distance = row["median_goal_distance_before_past_the_side"]
    concentration = row["median_concentration_per_dim"]
    ratio, baseline = row.get("ratio_at_zero_updates"), row.get("baseline")
    cells = [
        row["checkpoint"],
        "" if row["env_steps"] is None else f"{row['env_steps'] / 1e6:.1f} M",
        ", ".join(str(counts[kind]) for kind in KINDS),
        f"{row['success_rate']:.2f}",
        "" if distance is None else f"{distance:.2f}",
        f"{row['share_of_spheres_served']:.2f}, {row['median_nearest_wavelet_cells']:.2f}, "
        f"{row['share_of_spheres_at_rest']:.2f}, "
        f"{1000 * row['mean_approach_per_decision_m']:.2f}",
        f"{row['share_at_speed_limit']:.2f}, {row['share_at_amplitude_limit']:.2f}, "
        f"{row['mean_width_cells']:.2f}",
        "" if concentration is None else ", ".join(f"{c:.1f}" for c in concentration),
        ""
        if ratio is None
        else f"{ratio['kl_approx']:.4f}, {ratio['clip_fraction_0.2']:.3f}, "
        f"{ratio['clip_fraction_0.1']:.3f}",
        ""
        if baseline is None
        else f"{baseline['agent_spread']:.4f}, {baseline['action_effect']:.4f}",
    ]
    return "| " + " | ".join(cells) + " |"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("checkpoints", nargs="+", type=Path, help="last.pt or best.pt files")
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    parser.add_argument("--envs", type=int, default=64, help="environments per checkpoint")
    parser.add_argument("--decisions", type=int, default=384, help="decisions of the rollout")
    parser.add_argument("--seed", type=int, default=3)
    parser.add_argument(
        "--serve-radius",
        type=float,
        default=2.5,
        help="a sphere counts as served while a wavelet centre is within this many cells of it",
    )
    parser.add_argument(
        "--heuristic",
        action="store_true",
        help="add a row for the scripted heuristic on the first checkpoint's scene",
    )
    parser.add_argument(
        "--out", type=Path, default=Path(__file__).parent / "results" / "diagnose_policy.json"
    )
    args = parser.parse_args()
    if args.envs < 1 or args.decisions < 1:
        parser.error("--envs and --decisions must be at least 1")
    if not args.serve_radius > 0:
        parser.error(f"--serve-radius must be positive, got {args.serve_radius}")
    for path in args.checkpoints:
        if not path.is_file():
            parser.error(f"no checkpoint at {path}")
    device = torch.device(args.device)
    payload = {"date": date.today().isoformat(), "device": device_name(device), "rows": []}
    print(
        f"Policy diagnostics: {args.envs} environments x {args.decisions} decisions, "
        f"{payload['device']}"
    )
    print(
        "| checkpoint | env-steps | goal, past the side, thrown above, below | success "
        "| goal distance before past the side [m] "
        f"| spheres served (within {args.serve_radius} cells), nearest wavelet [cells], at rest, "
        "approach [mm / decision] "
        "| at speed limit, at amplitude limit, width "
        f"| median alpha + beta per action ({', '.join(ACTION_NAMES)}) "
        "| dropout alone: KL, clip fraction 0.2, 0.1 "
        "| baselines: spread across agents, effect of the actions |"
    )
    print("|---|---:|---|---:|---:|---|---|---|---|---|")
    for path in args.checkpoints:
        payload["rows"].append(diagnose(path, args, device))
        print(format_row(payload["rows"][-1]), flush=True)
        write_results(args.out, payload)
    if args.heuristic:
        scene = TerraShiftConfig(**load_checkpoint(args.checkpoints[0])["env_config"])
        payload["rows"].append(diagnose_heuristic(scene, args, device))
        print(format_row(payload["rows"][-1]), flush=True)
        write_results(args.out, payload)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
