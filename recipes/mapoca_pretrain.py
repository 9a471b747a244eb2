"""MA-POCA pretraining on batched TerraShift environments.

    python recipes/mapoca_pretrain.py                                  # the paper's scene
    python recipes/mapoca_pretrain.py --config-name mapoca_paper       # the paper's Table 1
    python recipes/mapoca_pretrain.py train.num_envs=1024 run.minutes=10 logger=csv
    python recipes/mapoca_pretrain.py run.resume=<run dir>/checkpoints/last.pt
    python recipes/mapoca_pretrain.py env=large curriculum=auto        # in stages from 15x15
    torchrun --standalone --nproc_per_node=4 recipes/mapoca_pretrain.py   # 4 GPUs, data-parallel

Config: recipes/configs/mapoca_pretrain.yaml (groups env, model, train, algo, loss, logger,
curriculum; the settings room is :mod:`terrashift_rl.training.settings`). Without a CUDA device,
run.device=auto sizes the run for the CPU (run.cpu_defaults: the small model, 32 environments,
one thread, five minutes) where the command line leaves a setting alone; a run from a checkpoint
(run.resume, run.pretrained) builds its model. Outputs (checkpoints, logs, resolved config) go to
Hydra's run directory.

:func:`train` is the run: config, setup (environments, networks, trainer with its loss and
optimiser, logger), the train loop, cleanup; :func:`launch` sizes the config for the machine
first. The finetuning recipe (recipes/mapoca_finetune.py) launches the same run.
Started by ``torchrun``, each process joins the process group (unless it is in it already; then
it stays), trains data-parallel on its own device with seed ``run.seed + rank``
(:mod:`terrashift_rl.training.distributed`) and leaves the group at the end; rank 0 alone logs,
shows progress and writes files. SIGINT or SIGTERM stops after the running iteration with a
checkpoint, without the final evaluation, and prints the command that resumes the run; the
resumed run goes on in the same folder (the config's ``hydra.run.dir``). Messages go through
Python's logging, which Hydra sends to the terminal and to ``<run dir>/<recipe>.log``.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import sys
import time
from collections.abc import Callable
from pathlib import Path

import hydra
import torch
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig, OmegaConf
from torchrl.envs import TransformedEnv
from tqdm import tqdm
from tqdm.contrib.logging import logging_redirect_tqdm

from terrashift_rl.modules import make_terrashift_networks
from terrashift_rl.sim import TerraShiftConfig
from terrashift_rl.training import distributed, make_trainer, make_training_env
from terrashift_rl.training.budget import iterate_until, planned_env_steps
from terrashift_rl.training.checkpoint import (
    RESUME_KEYS,
    WEIGHTS_KEYS,
    check_action_mode,
    check_resumable,
    last_state,
    load_checkpoint,
    network_settings,
    remove_stale_temporaries,
    save_checkpoint,
    update_best,
    weights_state,
)
from terrashift_rl.training.curriculum import Curriculum, CurriculumHook
from terrashift_rl.training.evaluation import evaluate_periodically, evaluation_scene, headline
from terrashift_rl.training.launch import (
    check_warp_cache,
    claim_run_folder,
    close_compile_workers,
    hydra_overrides_of_other_ranks,
    refusals_end_the_run,
    register_run_folder,
    resolve_device,
    resume_command,
    shown,
    size_for_the_machine,
    start_warp,
)
from terrashift_rl.training.loggers import close_logger, log_scalars, logger_run_id, make_logger
from terrashift_rl.training.settings import RecipeConfig, register_config_schemas
from terrashift_rl.training.signals import StopRequest

register_config_schemas()
register_run_folder()
log = logging.getLogger(Path(__file__).stem)


def train(
    cfg: DictConfig, *, run_dir: Path, resume_hint: Callable[[Path], str] | None = None
) -> Path:
    """Trains as the composed config ``cfg`` says, writing the checkpoints, logs and resolved
    config under ``run_dir``; returns the last checkpoint's path. A run stopped before its
    step target shows ``resume_hint(last checkpoint)``, the command that resumes it."""
    # --- config: every setting checked before anything is built ------------------------------
    settings = RecipeConfig.of(cfg)
    run = settings.run
    device = resolve_device(run.device, "run.device")
    start_warp(device)
    if run.threads is not None:
        torch.set_num_threads(run.threads)
    configs = {
        "env_config": dataclasses.asdict(settings.env),
        "model_config": dataclasses.asdict(settings.model),
        "curriculum_config": dataclasses.asdict(settings.curriculum),
    }
    curriculum = None
    if settings.curriculum.kind == "auto":  # stages from a small scene to env's
        curriculum = Curriculum(settings.env, settings.curriculum)
        curriculum.check_training(
            algo=settings.train.algo,
            teacher=settings.train.algo == "mapoca" and settings.train.loss.teacher_coeff > 0,
            num_envs=settings.train.num_envs,
        )
    resume = load_checkpoint(run.resume, required=RESUME_KEYS) if run.resume else None
    if resume is not None:
        train_config = dataclasses.asdict(settings.train)
        check_resumable(
            resume,
            {**configs, "train_config": train_config, "algo": settings.train.algo},
            path=run.resume,
        )
    pretrained = load_checkpoint(run.pretrained, required=WEIGHTS_KEYS) if run.pretrained else None
    if pretrained is not None:
        if network_settings(pretrained["model_config"]) != network_settings(
            configs["model_config"]
        ):
            raise ValueError(
                f"run.pretrained={run.pretrained} holds a network of another shape; use the "
                "model settings it was trained with (the recipes do when the command line sets "
                "none)"
            )
        check_action_mode(pretrained, settings.env, "run.pretrained")
    checkpoints = run_dir / "checkpoints"
    # a run killed while writing a checkpoint leaves its temporary file beside it
    folders = [checkpoints] if resume is None else [checkpoints, Path(run.resume).parent]
    for folder in folders if distributed.is_main_process() else []:
        for path in remove_stale_temporaries(folder):
            log.info(f"removed {path}, left by a checkpoint write that never finished")

    # --- setup: environments, networks, trainer (loss, optimiser), logger ---------------------
    joins = distributed.launched() and not distributed.is_distributed()
    if distributed.launched():  # one rank of torchrun's: its own device, seed and environments
        device = distributed.init_process_group(
            run.device,
            key="run.device",
            timeout=run.collective_timeout_s,
            timeout_key="run.collective_timeout_s",
        )
    main, seed = distributed.is_main_process(), run.seed + distributed.rank()
    # rank 0 alone evaluates and writes best.pt and snapshots
    window = run.best_window if main else 0
    snapshot_every = run.snapshot_every if main else None
    eval_every = run.eval_every if main else None
    torch.manual_seed(seed)
    networks = make_terrashift_networks(settings.model).to(device)

    def evaluation_env(scene: TerraShiftConfig) -> TransformedEnv:
        """Evaluation mode (no respawn, no shaping), the same scenes at every evaluation."""
        return make_training_env(
            evaluation_scene(scene),
            networks,
            num_envs=run.eval_episodes,
            device=device,
            seed=run.eval_seed,
        )

    num_envs, stages = settings.train.num_envs, None
    if curriculum is None:
        env = make_training_env(settings.env, networks, num_envs=num_envs, device=device, seed=seed)
    else:  # the current stage's mix of scenes; the hook advances it and holds its state
        if resume is not None:  # the environments of the checkpoint's stage
            curriculum.load_state_dict(resume["curriculum"])
        stages = CurriculumHook(
            curriculum,
            networks,
            evaluation_env if main else None,
            num_envs=num_envs,
            device=device,
            seed=seed,
            eval_seed=run.eval_seed,
        )
        env = stages.env
    trainer = make_trainer(env, networks, settings.train, scene_state=stages)
    if pretrained is not None:
        trainer.load_weights(pretrained)
    eval_env = eval_every and evaluation_env(settings.env)  # the target's, with a curriculum
    run_id, best, seconds_before = None, {"reward": -math.inf, "recent": []}, 0.0
    if resume is not None:
        trainer.load_state_dict(resume)
        run_id, best = resume["logger_run_id"], resume["best"]
        seconds_before = resume["run_seconds"]  # the earlier parts' time in the loop
        if main and resume.get("world_size", 1) != distributed.world_size():
            log.info(
                distributed.world_size_change(resume.get("world_size", 1), distributed.world_size())
            )
    logger = make_logger(settings.logger, run.name, run_dir, run_id) if main else None
    run_id = run_id or logger_run_id(logger)
    if main:
        OmegaConf.save(cfg, run_dir / "config.yaml")

    def evaluate_now(label: str) -> dict[str, float]:
        start = time.monotonic()
        scores = evaluate_periodically(
            eval_env,
            networks.actor,
            seed=run.eval_seed,
            sampled=run.eval_sampled,
            progress=label,
            policies=trainer.evaluation_policy,
        )
        return {**scores, "eval_seconds": time.monotonic() - start}

    def run_seconds() -> float:
        """The seconds spent in the training loop (evaluations and checkpoints included), a
        resumed run's earlier parts too."""
        return seconds_before + time.monotonic() - started

    def save_last() -> None:
        # on every rank: a collective
        state = last_state(trainer, configs, run_id, best, run_seconds())
        if main:
            save_checkpoint(state, last)

    # --- train loop ---------------------------------------------------------------------------
    last = checkpoints / "last.pt"
    started, steps_at_start = time.monotonic(), trainer.env_steps
    deadline = None if run.minutes is None else started + 60.0 * run.minutes
    per_iteration = settings.train.num_envs * settings.train.steps_per_iteration
    per_iteration *= distributed.world_size()
    planned = planned_env_steps(trainer.env_steps, per_iteration, run.total_env_steps)
    if main:
        limit = "" if run.minutes is None else f" or {run.minutes:g} minutes, whichever is first"
        log.info(f"{run.name}: {planned:,} env-steps{limit}; checkpoints in {shown(checkpoints)}")
        processes, minibatches = distributed.world_size(), settings.train.minibatches
        if processes > 1:
            log.info(
                f"{processes} processes of {num_envs:,} environments, each splitting its batch "
                f"into {trainer.minibatches} mini-batches per epoch (train.minibatches="
                f"{minibatches} x {processes}): an optimiser step averages "
                f"{num_envs // minibatches:,} sequences, as with one process"
            )
        if settings.train.compile:
            log.info(
                "torch.compile compiles the networks' update in the first iterations: about a "
                "minute on a machine's first run, seconds from Inductor's cache after it "
                "(train.compile=false runs them eagerly)"
            )
    progress = tqdm(
        total=planned if deadline is None else None,  # known after the first iteration
        initial=trainer.env_steps,
        unit="step",
        unit_scale=True,
        desc=run.name,
        dynamic_ncols=True,
        disable=not main,
    )
    goal_fraction = "-"  # the latest evaluation's goal fraction, for the progress bar
    postfix: dict[str, str] = {}  # what the progress bar shows beside the env-steps
    with logging_redirect_tqdm(), StopRequest(announce=main) as stop:
        try:
            if eval_env and pretrained is not None and resume is None:  # a finetune's zero-shot
                zero_shot = evaluate_now("evaluation of the pretrained weights")
                goal_fraction = f"{zero_shot['eval_goal_fraction']:.3f}"
                log.info(f"the pretrained weights: {headline(zero_shot, 'eval_')}")
                log_scalars(logger, zero_shot, trainer.env_steps)
            for metrics in iterate_until(
                trainer, total_env_steps=run.total_env_steps, deadline=deadline
            ):
                stop.activity = "the evaluation and writes after an iteration"
                metrics["run_seconds"] = run_seconds()  # this iteration's evaluation aside
                progress.update(trainer.env_steps - progress.n)
                if stages is not None:
                    stage = curriculum.stage
                    metrics.update(stages.after_iteration(trainer))
                    if main and curriculum.stage != stage:
                        log.info(
                            f"{curriculum.describe()} from {trainer.env_steps:,} env-steps (a "
                            f"goal fraction of {metrics['curriculum_eval_goal_fraction']:.3f} "
                            f"at stage {stage + 1})"
                        )
                    if "curriculum_start_eval_goal_fraction" in metrics:
                        start = headline(metrics, "curriculum_start_eval_")
                        log.info(f"stage 1's scene at {trainer.env_steps:,} env-steps: {start}")
                if eval_env and trainer.iteration % eval_every == 0:
                    metrics.update(evaluate_now("evaluation"))
                    goal_fraction = f"{metrics['eval_goal_fraction']:.3f}"
                log_scalars(logger, metrics, trainer.env_steps)
                if window:
                    reward = metrics["reward_per_decision"]
                    update_best(best, reward, window, trainer, configs, checkpoints / "best.pt")
                if trainer.iteration % run.checkpoint_every == 0:
                    save_last()
                if snapshot_every and trainer.iteration % snapshot_every == 0:
                    snapshot = checkpoints / f"iteration_{trainer.iteration:06d}.pt"
                    save_checkpoint(weights_state(trainer, configs), snapshot)
                # the bar's total is what the run will do: the step target, or the iterations
                # that the time left allows at the pace so far (evaluations and writes included)
                elapsed = time.monotonic() - started
                iterations = (trainer.env_steps - steps_at_start) // per_iteration
                progress.total = planned_env_steps(
                    trainer.env_steps,
                    per_iteration,
                    run.total_env_steps,
                    seconds_left=None if deadline is None else deadline - time.monotonic(),
                    seconds_per_iteration=elapsed / max(iterations, 1),
                )
                postfix = {
                    **({} if curriculum is None else {"stage": curriculum.describe(short=True)}),
                    "eval_goals": goal_fraction,
                    "reward": f"{metrics['reward_per_decision']:+.4f}",
                    "steps_per_s": f"{metrics['env_steps_per_s']:,.0f}",
                }
                progress.set_postfix(postfix)
                if distributed.any_process(stop.requested):  # every rank stops alike
                    break
                stop.activity = "the iteration"
            # between iterations: the state is consistent, the checkpoint resumes exactly
            stop.activity = "the checkpoint's write"
            save_last()
            stop.activity = "the run's cleanup, after its checkpoint"
            if eval_env and trainer.iteration % eval_every and not stop.requested:
                with stop.skippable("the final evaluation"):  # a signal skips it
                    final = evaluate_now("final evaluation (Ctrl-C skips it)")
                    log.info(
                        f"evaluation at {trainer.env_steps:,} env-steps: {headline(final, 'eval_')}"
                    )
                    log_scalars(logger, final, trainer.env_steps)
                    progress.set_postfix(postfix, eval_goals=f"{final['eval_goal_fraction']:.3f}")
        except KeyboardInterrupt:
            if main and last.exists():
                log.info(
                    f"interrupted during {stop.activity}; {shown(last)} is the last checkpoint"
                )
                if resume_hint is not None:
                    log.info(f"resume with: {resume_hint(last)}")
            elif main:
                log.info(f"interrupted during {stop.activity}, before a checkpoint was written")
            raise SystemExit(130) from None
        except FloatingPointError as error:
            if not main:  # every rank stops at the same iteration; rank 0 says why
                raise SystemExit(1) from None
            written = f"{last} is the last checkpoint written" if last.exists() else "no checkpoint"
            raise SystemExit(f"{error}\nstopped without saving that iteration; {written}") from None

        # --- cleanup --------------------------------------------------------------------------
        finally:
            progress.close()
            with stop.skippable("closing the logger"):
                close_logger(logger)
            if joins:  # leaves the process group as it found it
                distributed.destroy_process_group()
    if main:
        minutes = (time.monotonic() - started) / 60
        log.info(
            f"{trainer.env_steps:,} env-steps in {trainer.iteration} iterations; checkpoint "
            f"{shown(last)} ({minutes:.1f} minutes)"
        )
        if resume_hint is not None and trainer.env_steps < run.total_env_steps:
            log.info(f"resume with: {resume_hint(last)}")
    return last


def launch(cfg: DictConfig) -> Path:
    """:func:`train` with the config sized for the machine, in Hydra's run directory, which it
    holds (:func:`~terrashift_rl.training.launch.claim_run_folder`)."""
    check_warp_cache()
    cfg = size_for_the_machine(
        cfg,
        device_key="run.device",
        defaults_key="run.cpu_defaults",
        model_from=("run.resume", "run.pretrained"),  # the network must be the one they hold
    )
    run_dir = Path(HydraConfig.get().runtime.output_dir)
    with claim_run_folder(run_dir):
        try:
            return train(cfg, run_dir=run_dir, resume_hint=resume_command)
        finally:
            close_compile_workers()


@hydra.main(version_base=None, config_path="configs", config_name="mapoca_pretrain")
@refusals_end_the_run()
def main(cfg: DictConfig) -> None:
    launch(cfg)


if __name__ == "__main__":
    sys.argv.extend(hydra_overrides_of_other_ranks())  # under torchrun, rank 0 alone writes
    main()
