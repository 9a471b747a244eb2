"""Evaluation of a policy over one episode per environment, and the baseline policies' scores."""

from __future__ import annotations

import functools
from collections.abc import Callable

import torch
from tensordict import TensorDictBase
from torchrl.envs import EnvBase
from torchrl.envs.utils import ExplorationType, set_exploration_type
from tqdm.auto import tqdm

from terrashift_rl.envs.baselines import RandomPolicy, ScriptedHeuristicPolicy, ZeroPolicy
from terrashift_rl.envs.terrashift import TerraShiftEnv
from terrashift_rl.sim.config import TerraShiftConfig

Policy = Callable[[TensorDictBase], TensorDictBase]
"""Anything that writes ``("agents", "action")`` into the tensordict it is given."""

__all__ = [
    "Policy",
    "actor_policy",
    "evaluate",
    "evaluate_baselines",
    "evaluate_periodically",
    "evaluation_scene",
    "headline",
]

HEADLINE = (
    "goal_fraction",
    "success_rate",
    "out_of_bounds_per_episode",
    "mean_episode_length",
    "mean_reward_per_decision",
)
"""The metrics every score is reported with, the goal fraction first: a policy that keeps its
spheres still loses none and scores a high success rate, but not a high goal fraction."""


def headline(metrics: dict[str, float], prefix: str = "") -> str:
    """The :data:`HEADLINE` metrics of a score (keys ``prefix + name``) as one line.

    Example:
        >>> score = {"goal_fraction": 0.5, "success_rate": 0.75, "out_of_bounds_per_episode": 1,
        ...          "mean_episode_length": 212.5, "mean_reward_per_decision": 0.0123}
        >>> print(headline(score))  # doctest: +NORMALIZE_WHITESPACE
        goal fraction 0.5, success rate 0.75, out of bounds per episode 1,
        mean episode length 212.5, mean reward per decision 0.0123
    """
    return ", ".join(f"{name.replace('_', ' ')} {metrics[prefix + name]:.4g}" for name in HEADLINE)


def actor_policy(actor: Callable, exploration: ExplorationType) -> Policy:
    """``actor`` (a TorchRL actor) as a :data:`Policy` with its exploration type fixed:
    ``DETERMINISTIC`` acts with the distribution's mean, ``RANDOM`` samples."""

    def policy(td: TensorDictBase) -> TensorDictBase:
        with set_exploration_type(exploration):
            return actor(td)

    return policy


def _scene_config(env: EnvBase) -> TerraShiftConfig:
    """The TerraShift config of ``env`` or of the base env a TransformedEnv wraps."""
    base = getattr(env, "base_env", env)
    config = getattr(base, "config", None)
    if not isinstance(config, TerraShiftConfig):
        raise ValueError(
            f"evaluate needs a TerraShiftEnv (or a TransformedEnv around one), got "
            f"{type(env).__name__}"
        )
    return config


def evaluation_scene(config: TerraShiftConfig, *, respawn: bool = False) -> TerraShiftConfig:
    """The scene as an evaluation plays it: ``respawn`` as given (False: evaluation mode), and
    without the reward's shaping terms (:meth:`~TerraShiftConfig.without_shaping`), training
    aids, so that the reward per decision compares across recipes and with the baselines.

    Example:
        >>> scene = evaluation_scene(TerraShiftConfig(approach_scale=0.3, alignment_scale=0.2))
        >>> scene.respawn, scene.approach_scale, scene.alignment_scale
        (False, 0.0, 0.0)
    """
    return config.without_shaping().replace(respawn=respawn)


def evaluate(
    env: EnvBase,
    policy: Policy,
    *,
    episodes: int | None = None,
    progress: bool | str = True,
) -> dict[str, float]:
    """Runs exactly one episode in every environment of ``env`` and scores ``policy``.

    The environments are reset once, then stepped together with ``env.step_and_maybe_reset``
    until each has finished its first episode (``done``). In evaluation mode
    (``respawn=False``) an episode ends when every sphere is resolved or at the step limit;
    environments that finish early keep stepping with the rest (they are reset automatically),
    but their later steps are ignored. In training mode (respawn on) every episode runs to the
    step limit, so its reward per decision is the training metric (the paper's). Runs under
    ``torch.no_grad``.

    Args:
        env: a batched :class:`~terrashift_rl.envs.TerraShiftEnv`, or a TorchRL
            ``TransformedEnv`` wrapping one.
        policy: callable writing ``("agents", "action")`` into the tensordict it receives.
        episodes: number of episodes; must equal ``env``'s number of environments if given.
        progress: show a tqdm bar over the decisions (with the episodes finished), labelled
            ``evaluate`` or with the string given.

    Returns:
        ``goal_fraction``, goals over ``episodes * num_objects`` (the headline; above 1 in
        training mode when respawned spheres reach their goals); ``success_rate``, goals over
        resolved objects (goals plus out of bounds; 0 if nothing was resolved); ``episodes``;
        ``goals_per_episode``; ``out_of_bounds_per_episode``; ``mean_reward_per_decision``, the
        team reward averaged over each environment's decisions of its episode, then over the
        environments; ``mean_episode_length`` in decisions; ``terminated_fraction``, the share of
        episodes that ended with every sphere resolved rather than at the step limit;
        ``surface_work_per_episode``, the work the surface did on the spheres [J] (0 unless
        the scene has ``count_surface_work``; over ``goals_per_episode``, the actuator's
        energy per sphere delivered).

    Raises:
        ValueError: if ``env`` is not a TerraShift environment, is not batched,
            ``episodes`` differs from its number of environments, or ``policy`` acted with NaN
            or infinity (:meth:`~terrashift_rl.envs.terrashift.TerraShiftEnv.check_actions`).
    """
    config = _scene_config(env)
    if len(env.batch_size) != 1:
        raise ValueError(f"evaluate needs a batch of environments, got batch {env.batch_size}")
    num_envs = env.batch_size[0]
    if episodes is not None and episodes != num_envs:
        raise ValueError(
            f"evaluate runs one episode per environment: episodes ({episodes}) must equal the "
            f"number of environments ({num_envs})"
        )
    device = env.device
    running = torch.ones(num_envs, dtype=torch.bool, device=device)
    length = torch.zeros(num_envs, dtype=torch.long, device=device)
    reward_sum = torch.zeros(num_envs, dtype=torch.float64, device=device)
    goals = torch.zeros(num_envs, dtype=torch.long, device=device)
    lost = torch.zeros(num_envs, dtype=torch.long, device=device)
    terminated = torch.zeros(num_envs, dtype=torch.bool, device=device)
    work = torch.zeros(num_envs, dtype=torch.float64, device=device)

    bar = tqdm(
        total=config.max_episode_steps,
        desc=progress if isinstance(progress, str) else "evaluate",
        unit="decision",
        disable=not progress,
    )
    with torch.no_grad(), bar:  # closed also when Ctrl-C ends the evaluation
        td = env.reset()
        # every environment ends within max_episode_steps decisions (truncation)
        for _ in range(config.max_episode_steps):
            td = policy(td)
            out, td = env.step_and_maybe_reset(td)
            nxt = out.get("next")
            reward = nxt.get(("agents", "reward"))[..., 0, 0]
            done = nxt.get("done").reshape(num_envs)
            length += running.long()
            reward_sum += torch.where(running, reward.double(), 0.0)
            finished = running & done
            goals = torch.where(finished, nxt.get("episode_goals").reshape(num_envs), goals)
            lost = torch.where(finished, nxt.get("episode_out_of_bounds").reshape(num_envs), lost)
            spent = nxt.get("episode_surface_work").reshape(num_envs).double()
            work = torch.where(finished, spent, work)
            terminated |= finished & nxt.get("terminated").reshape(num_envs)
            running &= ~done
            left = int(running.sum())
            bar.set_postfix_str(f"{num_envs - left}/{num_envs} episodes done", refresh=False)
            bar.update()
            if left == 0:
                break
    getattr(env, "base_env", env).check_actions()
    if running.any():  # cannot happen: truncation ends every episode at the step limit
        raise RuntimeError(
            f"{int(running.sum())} environment(s) did not finish within max_episode_steps"
        )

    total_goals = float(goals.sum())
    total_lost = float(lost.sum())
    resolved = total_goals + total_lost
    return {
        "goal_fraction": total_goals / (num_envs * config.num_objects),
        "success_rate": total_goals / resolved if resolved > 0 else 0.0,
        "episodes": float(num_envs),
        "goals_per_episode": total_goals / num_envs,
        "out_of_bounds_per_episode": total_lost / num_envs,
        "mean_reward_per_decision": float((reward_sum / length.double()).mean()),
        "mean_episode_length": float(length.double().mean()),
        "terminated_fraction": float(terminated.double().mean()),
        "surface_work_per_episode": float(work.sum()) / num_envs,
    }


def evaluate_baselines(
    config: TerraShiftConfig,
    *,
    num_envs: int,
    device: str | torch.device = "cpu",
    seed: int = 0,
    progress: bool = False,
    respawn: bool = False,
) -> dict[str, dict[str, float]]:
    """Scores the random, zero and scripted heuristic policies with :func:`evaluate`.

    Each policy gets a fresh environment of :func:`evaluation_scene` and the same
    ``seed``, so all three face the same initial scenes (goals, first sphere, wavelets);
    the random policy's generator is seeded with ``seed`` too. The scene observes the object
    sequence and renders no camera, whatever ``config`` says: the heuristic reads the
    objects, a privileged view when the policy learns from pixels, and no baseline reads the
    camera (the scenes are the same: the camera draws no random numbers).

    Args:
        config: the scene, played as :func:`evaluation_scene` with ``respawn``.
        num_envs: environments, hence episodes, per policy.
        device: where to simulate.
        seed: seed of the environments and of the random policy.
        progress: show a tqdm bar per policy, labelled with its name.
        respawn: False for evaluation mode, True for training mode (episodes run to the step
            limit).

    Returns:
        ``{"random": metrics, "zero": metrics, "heuristic": metrics}``, each as returned by
        :func:`evaluate`.

    Example:
        >>> cfg = TerraShiftConfig(max_episode_steps=8)
        >>> scores = evaluate_baselines(cfg, num_envs=2, seed=0)
        >>> sorted(scores), scores["zero"]["episodes"]
        (['heuristic', 'random', 'zero'], 2.0)
    """
    config = evaluation_scene(config, respawn=respawn).replace(
        observe_objects=True, privileged_objects=False, camera_resolution=0
    )
    policies: dict[str, Policy] = {
        "random": RandomPolicy(seed=seed),
        "zero": ZeroPolicy(),
        "heuristic": ScriptedHeuristicPolicy(config),
    }
    results = {}
    for name, policy in policies.items():
        env = TerraShiftEnv(config, num_envs=num_envs, device=device, seed=seed)
        results[name] = evaluate(env, policy, progress=progress and f"baseline {name}")
    return results


def evaluate_periodically(
    env: EnvBase,
    actor: Callable,
    *,
    seed: int,
    sampled: bool = False,
    progress: str | None = None,
    policies: Callable[[ExplorationType], Policy] | None = None,
) -> dict[str, float]:
    """Scores ``actor``'s mean action (:func:`evaluate`) on the same scenes at every call:
    ``env`` is reseeded with ``seed`` first, so that the scores of one run's successive
    evaluations differ only by the policy. Returns :data:`HEADLINE`'s metrics, prefixed
    ``eval_``; networks in the actor are left in eval mode (no dropout).

    With ``sampled``, the policy's sampled actions are scored too, on the same scenes, with
    the metrics prefixed ``eval_sampled_``: they draw from torch's generator seeded with
    ``seed`` inside a fork of it, so that training's random stream is left as it was.
    ``progress`` labels a bar over each evaluation's decisions; none without it.
    ``policies`` gives ``actor``'s policy of an exploration type, :func:`actor_policy` if
    None; a trainer's :meth:`~terrashift_rl.training.trainer.OnPolicyTrainer.evaluation_policy`
    replays it as a CUDA graph kept from one evaluation to the next."""
    if policies is None:
        policies = functools.partial(actor_policy, actor)
    env.set_seed(seed)
    actor.eval()
    mean = policies(ExplorationType.DETERMINISTIC)
    metrics = evaluate(env, mean, progress=progress or False)
    scores = {f"eval_{name}": metrics[name] for name in HEADLINE}
    if sampled:
        device = torch.device(env.device)
        cuda = []
        if device.type == "cuda":
            cuda = [torch.cuda.current_device() if device.index is None else device.index]
        with torch.random.fork_rng(devices=cuda):
            torch.manual_seed(seed)
            env.set_seed(seed)
            samples = policies(ExplorationType.RANDOM)
            metrics = evaluate(env, samples, progress=progress and f"{progress} (samples)")
        scores.update({f"eval_sampled_{name}": metrics[name] for name in HEADLINE})
    return scores
