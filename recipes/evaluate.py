"""Scores a trained MA-POCA policy and the baselines (evaluation mode by default), records a video.

    python recipes/evaluate.py checkpoint=<run dir>/checkpoints/last.pt
    python recipes/evaluate.py checkpoint=last.pt episodes=512 video.steps=0
    python recipes/evaluate.py respawn=true     # training mode: the paper's reward per decision

Writes ``evaluation.json`` (success rate, goals and out-of-bounds per episode, mean reward per
decision; for the policy's mean action, for its samples, and for each baseline) and a video of
one environment into Hydra's run directory, with a progress bar per policy scored and for the
video. Without a CUDA device, device=auto scores 16 episodes and records a shorter video on one
thread (cpu_defaults: half a minute on two cores, docs/training.md) unless the command line
sets them.
"""

from __future__ import annotations

import dataclasses
import json
import logging
from pathlib import Path

import hydra
import torch
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig
from torchrl.envs.utils import ExplorationType

from terrashift_rl.modules import TerraShiftModelConfig, make_terrashift_networks
from terrashift_rl.sim import TerraShiftConfig
from terrashift_rl.training import make_training_env
from terrashift_rl.training.checkpoint import WEIGHTS_KEYS, check_action_mode, load_checkpoint
from terrashift_rl.training.evaluation import (
    actor_policy,
    evaluate,
    evaluate_baselines,
    evaluation_scene,
    headline,
)
from terrashift_rl.training.launch import (
    check_warp_cache,
    refusals_end_the_run,
    resolve_device,
    shown,
    size_for_the_machine,
    start_warp,
)
from terrashift_rl.training.settings import EvaluateConfig, register_config_schemas

register_config_schemas()
log = logging.getLogger(Path(__file__).stem)


@hydra.main(version_base=None, config_path="configs", config_name="evaluate")
@refusals_end_the_run()
def main(cfg: DictConfig) -> None:
    check_warp_cache()
    cfg = size_for_the_machine(cfg, device_key="device", defaults_key="cpu_defaults")
    settings = EvaluateConfig.of(cfg)  # every setting checked, naming a bad one
    device = resolve_device(settings.device, "device")
    start_warp(device)
    if settings.threads is not None:
        torch.set_num_threads(settings.threads)
    run_dir = Path(HydraConfig.get().runtime.output_dir)
    checkpoint = (
        load_checkpoint(settings.checkpoint, required=WEIGHTS_KEYS) if settings.checkpoint else None
    )
    if checkpoint is not None and settings.scene_from_checkpoint:
        scene = TerraShiftConfig(**checkpoint["env_config"])
    else:
        scene = settings.env
        if checkpoint is not None:
            check_action_mode(checkpoint, scene, "checkpoint")
    # the surface's work on the spheres, the actuator's energy, is counted for every policy
    scene = evaluation_scene(scene, respawn=settings.respawn).replace(count_surface_work=True)
    results: dict = {"scene": dataclasses.asdict(scene), "episodes": settings.episodes}

    networks = None
    if checkpoint is not None:
        networks = make_terrashift_networks(TerraShiftModelConfig(**checkpoint["model_config"]))
        networks.load_state_dict(checkpoint["networks"])
        networks.to(device).eval()
        results["checkpoint"] = str(settings.checkpoint)
        results["checkpoint_env_steps"] = checkpoint["env_steps"]
        with torch.no_grad():
            for name, label, exploration in (
                ("deterministic", "policy", ExplorationType.DETERMINISTIC),
                ("stochastic", "policy (samples)", ExplorationType.RANDOM),
            ):
                env = make_training_env(
                    scene, networks, num_envs=settings.episodes, device=device, seed=settings.seed
                )
                torch.manual_seed(settings.seed)  # the sampled actions draw from torch's generators
                policy = actor_policy(networks.actor, exploration)
                results[name] = evaluate(env, policy, progress=label)
                log.info(f"{label}: {headline(results[name])}")
    if settings.baselines:
        results["baselines"] = evaluate_baselines(
            scene,
            num_envs=settings.episodes,
            device=device,
            seed=settings.seed,
            respawn=settings.respawn,
            progress=True,
        )
        for name, metrics in results["baselines"].items():
            log.info(f"baseline {name}: {headline(metrics)}")
    out = run_dir / "evaluation.json"
    out.write_text(json.dumps(results, indent=2))
    log.info(f"wrote {shown(out)}")

    video = None
    if settings.video.steps > 0:
        from terrashift_rl.envs.render import record_rollout, save_video

        if networks is not None:
            env = make_training_env(scene, networks, num_envs=1, device=device, seed=settings.seed)
            policy = actor_policy(networks.actor, ExplorationType.DETERMINISTIC)
        else:
            from terrashift_rl.envs import TerraShiftEnv
            from terrashift_rl.envs.baselines import ScriptedHeuristicPolicy

            env = TerraShiftEnv(scene, num_envs=1, device=device, seed=settings.seed)
            policy = ScriptedHeuristicPolicy(scene)
        with torch.no_grad():
            frames = record_rollout(
                env, policy, steps=settings.video.steps, every=settings.video.every
            )
        video = save_video(
            frames, run_dir / f"rollout.{settings.video.format}", fps=settings.video.fps
        )
        log.info(f"wrote {shown(video)}")

    if settings.wandb:
        import wandb

        run = wandb.init(
            project="terrashift_rl",
            dir=str(run_dir),
            mode="offline",
            job_type="evaluation",
            config=results,
            settings=wandb.Settings(silent=True, console="off"),
        )
        scored = {
            **{name: results[name] for name in ("deterministic", "stochastic") if name in results},
            **{f"baseline_{name}": value for name, value in results.get("baselines", {}).items()},
        }
        run.log({f"{name}/{key}": value for name, m in scored.items() for key, value in m.items()})
        if video is not None:
            run.log({"rollout": wandb.Video(str(video), format=settings.video.format)})
        run.finish()


if __name__ == "__main__":
    main()
