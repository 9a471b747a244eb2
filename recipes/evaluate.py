"""Scores a trained MA-POCA policy and the baselines (evaluation mode by default), records a video.

    python recipes/evaluate.py checkpoint=<run dir>/checkpoints/last.pt
    python recipes/evaluate.py checkpoint=last.pt episodes=512 video.steps=0
    python recipes/evaluate.py respawn=true     # training mode: the paper's reward per decision

Writes ``evaluation.json`` (success rate, goals and out-of-bounds per episode, mean reward per
decision; for the policy's mean action, for its samples, and for each baseline) and a video of
one environment into Hydra's run directory. Without a CUDA device, device=auto scores fewer
episodes (cpu_defaults) unless the command line sets them.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import hydra
import torch
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig
from torchrl.envs.utils import ExplorationType

from terrashift_rl.modules import TerraShiftModelConfig, make_terrashift_networks
from terrashift_rl.sim import TerraShiftConfig
from terrashift_rl.training import load_checkpoint, make_training_env
from terrashift_rl.training.evaluation import (
    actor_policy,
    evaluate,
    evaluate_baselines,
    evaluation_scene,
)
from terrashift_rl.training.run import (
    BOOLEAN,
    OVERRIDES,
    POSITIVE,
    TEXT,
    WEIGHTS_KEYS,
    check_action_mode,
    check_settings,
    integer,
    one_of,
    or_null,
    register_config_schemas,
    resolve_device,
    size_for_the_machine,
    structured,
)

register_config_schemas()

SETTINGS = {
    "checkpoint": or_null(TEXT, "the baselines alone"),
    "scene_from_checkpoint": BOOLEAN,
    "episodes": integer(1),
    "respawn": (BOOLEAN[0], "false (evaluation mode) or true (training mode)"),
    "baselines": BOOLEAN,
    "seed": integer(0),
    "video.steps": integer(0),
    "video.every": integer(1),
    "video.fps": POSITIVE,
    "video.format": one_of("mp4", "gif"),
    "wandb": BOOLEAN,
    "cpu_defaults": OVERRIDES,
}
"""The rules of every setting but ``device`` (:func:`~terrashift_rl.training.run.resolve_device`)
and the ``env`` group's (:class:`~terrashift_rl.sim.config.TerraShiftConfig`)."""


@hydra.main(version_base=None, config_path="configs", config_name="evaluate")
def main(cfg: DictConfig) -> None:
    cfg = size_for_the_machine(cfg, device_key="device", defaults_key="cpu_defaults")
    check_settings(cfg, SETTINGS)
    device = resolve_device(cfg.device, "device")
    run_dir = Path(HydraConfig.get().runtime.output_dir)
    checkpoint = load_checkpoint(cfg.checkpoint, required=WEIGHTS_KEYS) if cfg.checkpoint else None
    if checkpoint is not None and cfg.scene_from_checkpoint:
        scene = TerraShiftConfig(**checkpoint["env_config"])
    else:
        scene = structured(TerraShiftConfig, cfg.env, "env")
        if checkpoint is not None:
            check_action_mode(checkpoint, scene, "checkpoint")
    scene = evaluation_scene(scene, respawn=cfg.respawn)
    results: dict = {"scene": dataclasses.asdict(scene), "episodes": cfg.episodes}

    networks = None
    if checkpoint is not None:
        networks = make_terrashift_networks(TerraShiftModelConfig(**checkpoint["model_config"]))
        networks.load_state_dict(checkpoint["networks"])
        networks.to(device).eval()
        results["checkpoint"] = str(cfg.checkpoint)
        results["checkpoint_env_steps"] = checkpoint["env_steps"]
        with torch.no_grad():
            for name, exploration in (
                ("deterministic", ExplorationType.DETERMINISTIC),
                ("stochastic", ExplorationType.RANDOM),
            ):
                env = make_training_env(
                    scene, networks, num_envs=cfg.episodes, device=device, seed=cfg.seed
                )
                torch.manual_seed(cfg.seed)  # the sampled actions draw from torch's generators
                results[name] = evaluate(env, actor_policy(networks.actor, exploration))
                print(f"policy ({name}): {results[name]}")
    if cfg.baselines:
        results["baselines"] = evaluate_baselines(
            scene, num_envs=cfg.episodes, device=device, seed=cfg.seed, respawn=cfg.respawn
        )
        for name, metrics in results["baselines"].items():
            print(f"baseline {name}: {metrics}")
    out = run_dir / "evaluation.json"
    out.write_text(json.dumps(results, indent=2))
    print(f"wrote {out}")

    video = None
    if cfg.video.steps > 0:
        from terrashift_rl.envs.render import record_rollout, save_video

        if networks is not None:
            env = make_training_env(scene, networks, num_envs=1, device=device, seed=cfg.seed)
            policy = actor_policy(networks.actor, ExplorationType.DETERMINISTIC)
        else:
            from terrashift_rl.envs import TerraShiftEnv
            from terrashift_rl.envs.baselines import ScriptedHeuristicPolicy

            env = TerraShiftEnv(scene, num_envs=1, device=device, seed=cfg.seed)
            policy = ScriptedHeuristicPolicy(scene)
        with torch.no_grad():
            frames = record_rollout(env, policy, steps=cfg.video.steps, every=cfg.video.every)
        video = save_video(frames, run_dir / f"rollout.{cfg.video.format}", fps=cfg.video.fps)
        print(f"wrote {video}")

    if cfg.wandb:
        import wandb

        run = wandb.init(
            project="terrashift_rl",
            dir=str(run_dir),
            mode="offline",
            job_type="evaluation",
            config=results,
        )
        scored = {
            **{name: results[name] for name in ("deterministic", "stochastic") if name in results},
            **{f"baseline_{name}": value for name, value in results.get("baselines", {}).items()},
        }
        run.log({f"{name}/{key}": value for name, m in scored.items() for key, value in m.items()})
        if video is not None:
            run.log({"rollout": wandb.Video(str(video), format=cfg.video.format)})
        run.finish()


if __name__ == "__main__":
    main()
