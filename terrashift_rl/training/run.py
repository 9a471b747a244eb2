"""A training run as the recipes drive it from their Hydra config: settings checked at start-up,
sizes for a machine without CUDA, the loop with its checkpoints, evaluations and signals.

:func:`run_training` is the pretraining and finetuning recipes' run: config, then setup
(environments, networks, trainer with its loss and optimiser, logger), then the loop, then
cleanup. The rest is what the recipes share: the rules of the ``run``, ``logger`` and evaluation
settings (:func:`check_settings`), the device setting (:func:`resolve_device`), the CPU-sized
defaults of a run on a machine without CUDA (:func:`size_for_the_machine`), the checks that a
checkpoint can continue a run (:func:`check_resumable`) and what each checkpoint holds.
"""

from __future__ import annotations

import dataclasses
import json
import math
import shlex
import signal
import time
import typing
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import torch
from hydra import compose
from hydra.core.config_store import ConfigStore
from hydra.core.hydra_config import HydraConfig
from hydra.core.override_parser.overrides_parser import OverridesParser
from hydra.errors import OverrideParseException
from omegaconf import DictConfig, OmegaConf
from torchrl.record.loggers import Logger
from tqdm import tqdm

from terrashift_rl.modules import TerraShiftModelConfig, make_terrashift_networks
from terrashift_rl.sim import TerraShiftConfig
from terrashift_rl.training import distributed
from terrashift_rl.training.checkpoint import (
    load_checkpoint,
    remove_stale_temporaries,
    save_checkpoint,
)
from terrashift_rl.training.evaluation import evaluate_periodically, evaluation_scene
from terrashift_rl.training.trainer import (
    LOSS_SETTINGS,
    MAPOCATrainer,
    TrainConfig,
    iterate_until,
    make_training_env,
    setting_name,
)

__all__ = [
    "BOOLEAN",
    "OVERRIDES",
    "POSITIVE",
    "RENAMED_TRAIN_SETTINGS",
    "RESUME_KEYS",
    "RUN_SETTINGS",
    "TEXT",
    "WEIGHTS_KEYS",
    "LossSettings",
    "StopRequest",
    "TrainSettings",
    "check_resumable",
    "check_settings",
    "cpu_overrides",
    "fields_of",
    "hydra_overrides_of_other_ranks",
    "integer",
    "one_of",
    "or_null",
    "register_config_schemas",
    "resolve_device",
    "run_training",
    "size_for_the_machine",
    "structured",
    "train_config_of",
]


def fields_of(cls: type, names: Sequence[str], name: str) -> type:
    """A dataclass named ``name`` with the fields ``names`` of the dataclass ``cls``: their
    types and defaults, so a schema for part of ``cls`` takes them from ``cls`` alone.

    Example:
        >>> fields_of(TrainConfig, ["gamma", "lmbda"], "Discounting")()
        Discounting(gamma=0.95, lmbda=0.92)
    """
    types = typing.get_type_hints(cls)
    fields = {field.name: field for field in dataclasses.fields(cls)}
    return dataclasses.make_dataclass(
        name,
        [
            (
                field,
                types[field],
                dataclasses.field(
                    default=fields[field].default, default_factory=fields[field].default_factory
                ),
            )
            for field in names
        ],
    )


TrainSettings = fields_of(
    TrainConfig,
    [field.name for field in dataclasses.fields(TrainConfig) if field.name not in LOSS_SETTINGS],
    "TrainSettings",
)
TrainSettings.__module__ = __name__
TrainSettings.__doc__ = """The ``train`` config group's schema: the fields of
:class:`~terrashift_rl.training.trainer.TrainConfig` outside
:data:`~terrashift_rl.training.trainer.LOSS_SETTINGS`."""
LossSettings = fields_of(TrainConfig, LOSS_SETTINGS, "LossSettings")
LossSettings.__module__ = __name__
LossSettings.__doc__ = """The ``loss`` config group's schema: the fields of
:class:`~terrashift_rl.training.trainer.TrainConfig` in
:data:`~terrashift_rl.training.trainer.LOSS_SETTINGS`."""


def register_config_schemas() -> None:
    """Registers the ``schema`` option of the ``env``, ``model``, ``train`` and ``loss`` config
    groups: the group files name the fields they change, the dataclasses supply the others with
    their defaults and types, so every field can be set as ``group.field=value`` and Hydra
    refuses a key the group lacks. ``train`` and ``loss`` split the fields of
    :class:`~terrashift_rl.training.trainer.TrainConfig` (:class:`TrainSettings`,
    :class:`LossSettings`); ``model`` also has ``schema_small``, the typed
    :meth:`~terrashift_rl.modules.TerraShiftModelConfig.small` preset."""
    store = ConfigStore.instance()
    store.store(group="env", name="schema", node=TerraShiftConfig)
    store.store(group="model", name="schema", node=TerraShiftModelConfig)
    store.store(group="model", name="schema_small", node=TerraShiftModelConfig.small())
    store.store(group="train", name="schema", node=TrainSettings)
    store.store(group="loss", name="schema", node=LossSettings)


def train_config_of(cfg: DictConfig) -> TrainConfig:
    """The :class:`~terrashift_rl.training.trainer.TrainConfig` that the ``train`` and ``loss``
    config groups of ``cfg`` set; a key that its group lacks is named (:func:`structured`)."""
    train = structured(TrainSettings, cfg.train, "train")
    loss = structured(LossSettings, cfg.loss, "loss")
    return TrainConfig(**dataclasses.asdict(train), **dataclasses.asdict(loss))


def structured(cls: type, values: Any, group: str):
    """Builds a config dataclass from a config group, naming unknown keys on failure.

    Example:
        >>> structured(TerraShiftConfig, {"max_episode_steps": 64}, "env").max_episode_steps
        64
        >>> structured(TerraShiftConfig, {"grid_sise": 20}, "env")
        Traceback (most recent call last):
        ...
        ValueError: unknown key(s) ['grid_sise'] in config group 'env'; known: [...]
    """
    if isinstance(values, DictConfig):
        values = OmegaConf.to_container(values, resolve=True)
    known = {field.name for field in dataclasses.fields(cls)}
    unknown = sorted(set(values) - known)
    if unknown:
        raise ValueError(
            f"unknown key(s) {unknown} in config group '{group}'; known: {sorted(known)}"
        )
    return cls(**values)


# What evaluate.py and finetuning read (weights_state); resuming needs the trainer's state too.
WEIGHTS_KEYS = ("networks", "env_config", "model_config", "env_steps")
RESUME_KEYS = (*WEIGHTS_KEYS, "optimizer", "train_config", "simulator", "carry")


# --- settings ------------------------------------------------------------------------------------
Rule = tuple[Callable[[Any], bool], str]
"""A setting's rule: a test of its value and the text that says what the test allows."""


def integer(minimum: int) -> Rule:
    """An integer (not a boolean) at least ``minimum``."""
    return (
        lambda value: isinstance(value, int) and not isinstance(value, bool) and value >= minimum,
        f"an integer >= {minimum}",
    )


def one_of(*options: Any) -> Rule:
    """One of ``options``."""
    return (
        lambda value: value in options,
        ", ".join(map(str, options[:-1])) + f" or {options[-1]}",
    )


def or_null(rule: Rule, meaning: str) -> Rule:
    """``rule``, or null, which means ``meaning``."""
    test, allowed = rule
    return (lambda value: value is None or test(value), f"{allowed} or null ({meaning})")


POSITIVE: Rule = (
    lambda value: (
        isinstance(value, int | float)
        and not isinstance(value, bool)
        and math.isfinite(value)
        and value > 0
    ),
    "a finite number > 0",
)
BOOLEAN: Rule = (lambda value: isinstance(value, bool), "true or false")
TEXT: Rule = (lambda value: isinstance(value, str) and value != "", "a non-empty string")
OVERRIDES: Rule = (
    lambda value: (
        isinstance(value, Sequence)
        and not isinstance(value, str)
        and all(isinstance(item, str) and "=" in item for item in value)
    ),
    "a list of overrides (key=value)",
)

RUN_SETTINGS: dict[str, Rule] = {
    "run.name": TEXT,
    "run.seed": integer(0),
    "run.cpu_defaults": OVERRIDES,
    "run.total_env_steps": integer(1),
    "run.minutes": or_null(POSITIVE, "no time limit"),
    "run.checkpoint_every": integer(1),
    "run.best_window": (integer(0)[0], "an integer >= 0 (0: no best.pt)"),
    "run.snapshot_every": or_null(integer(1), "no snapshots"),
    "run.eval_every": or_null(integer(1), "no evaluation"),
    "run.eval_episodes": integer(1),
    "run.eval_seed": integer(0),
    "run.eval_sampled": BOOLEAN,
    "run.resume": or_null(TEXT, "a fresh start"),
    "run.pretrained": or_null(TEXT, "no pretrained weights"),
    "logger.kind": one_of("wandb", "csv", "tensorboard", "none"),
}
"""The rules of the ``run`` and ``logger`` settings (``run.device``: :func:`resolve_device`)."""


def check_settings(cfg: DictConfig, rules: dict[str, Rule]) -> None:
    """Raises ``ValueError`` naming the first setting of ``cfg`` that breaks its rule, with its
    value and what the rule allows.

    Example:
        >>> check_settings(OmegaConf.create({"run": {"seed": -1}}), {"run.seed": integer(0)})
        Traceback (most recent call last):
        ...
        ValueError: run.seed must be an integer >= 0, got -1
    """
    for key, (test, allowed) in rules.items():
        value = OmegaConf.select(cfg, key)
        if not test(value):
            raise ValueError(f"{key} must be {allowed}, got {value!r}")


def resolve_device(name: Any, key: str) -> torch.device:
    """The device setting ``key``: ``auto`` (CUDA when present, else the CPU), ``cpu``, ``cuda``
    or ``cuda:<index>``; raises ``ValueError`` naming ``key`` for anything else or for a CUDA
    device this machine lacks."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        device = torch.device(name) if isinstance(name, str) else None
    except RuntimeError:
        device = None
    if device is None or device.type not in ("cpu", "cuda"):
        raise ValueError(f"{key} must be auto, cpu, cuda or cuda:<index>, got {name!r}")
    if device.type == "cuda" and (device.index or 0) >= torch.cuda.device_count():
        raise ValueError(
            f"{key}={name}, but this machine has {torch.cuda.device_count()} CUDA device(s); "
            f"use {key}=auto or {key}=cpu"
        )
    return device


# --- sizes for a machine without CUDA ------------------------------------------------------------
def _keys(overrides: Sequence[str]) -> list[str]:
    """The key or config group that each Hydra override sets (``+``, ``++`` and ``~`` aside)."""
    return [parsed.key_or_group for parsed in OverridesParser.create().parse_overrides(overrides)]


def cpu_overrides(defaults: Sequence[str], given: Sequence[str]) -> list[str]:
    """The overrides of ``defaults`` that the command line's overrides ``given`` leave alone: a
    default is dropped when a given override sets its key, a key inside it (``model.embed_dim``
    for ``model=small``) or the config group it lies in (``train=throughput`` for
    ``train.num_envs=32``).

    Example:
        >>> defaults = ["model=small", "train.num_envs=32", "run.eval_episodes=16"]
        >>> cpu_overrides(defaults, ["env=finetune", "run.seed=3"])
        ['model=small', 'train.num_envs=32', 'run.eval_episodes=16']
        >>> cpu_overrides(defaults, ["model.embed_dim=64", "train=throughput"])
        ['run.eval_episodes=16']
    """
    given_keys = _keys(given)

    def overlaps(key: str, other: str) -> bool:
        return key == other or key.startswith(f"{other}.") or other.startswith(f"{key}.")

    return [
        default
        for default, key in zip(defaults, _keys(defaults), strict=True)
        if not any(overlaps(key, other) for other in given_keys)
    ]


def size_for_the_machine(
    cfg: DictConfig, *, device_key: str, defaults_key: str, model_from: Sequence[str] = ()
) -> DictConfig:
    """``cfg``, recomposed with the CPU-sized overrides ``defaults_key`` lists
    (:func:`cpu_overrides`) when ``device_key`` is ``auto`` on a machine without CUDA; says so in
    one line. Settings given on the command line are kept; ``device_key=cpu`` keeps them all.

    ``model_from`` names the settings of checkpoints whose weights the run loads (``run.resume``,
    ``run.pretrained``): the first one set gives the model settings, on any device, for the
    network must be the one it holds. They rank like the CPU-sized overrides (``model=small``
    gives way to them), below the command line: a model given there is built as given.
    Needs Hydra's app context (``@hydra.main``): the command line is its task overrides."""
    sizing = OmegaConf.select(cfg, device_key) == "auto" and not torch.cuda.is_available()
    source = next((key for key in model_from if isinstance(OmegaConf.select(cfg, key), str)), None)
    if not sizing and source is None:
        return cfg
    hydra_config = HydraConfig.get()
    given = list(hydra_config.overrides.task)
    pinned, changed = [], []
    if source is not None:
        saved = load_checkpoint(OmegaConf.select(cfg, source), required=("model_config",))
        model = {key: value for key, value in saved["model_config"].items() if key in cfg.model}
        texts = {hydra_override(f"model.{key}", value): key for key, value in model.items()}
        pinned = cpu_overrides(list(texts), given)
        changed = [texts[text] for text in pinned if cfg.model[texts[text]] != model[texts[text]]]
    sized = []
    if sizing:
        check_settings(cfg, {defaults_key: OVERRIDES})
        defaults = list(OmegaConf.select(cfg, defaults_key))
        try:
            sized = cpu_overrides(defaults, [*pinned, *given])
        except OverrideParseException as error:
            raise ValueError(
                f"{defaults_key}={defaults} holds an override Hydra cannot read: {error}"
            ) from None
        note = f" with the model of {source}" if pinned else ""
        if distributed.is_main_process():
            print(
                f"no CUDA device: a CPU-sized run ({' '.join(sized)}){note}; set {device_key}=cpu "
                "to keep the configured sizes"
                if sized
                else f"no CUDA device: running on the CPU with the configured sizes{note}"
            )
    elif changed and distributed.is_main_process():
        print(f"the model of {source}: it differs from the configured one in {', '.join(changed)}")
    if not sized and not changed:
        return cfg
    return compose(config_name=hydra_config.job.config_name, overrides=[*sized, *pinned, *given])


def hydra_overrides_of_other_ranks() -> list[str]:
    """Hydra overrides for the command line of a torchrun rank other than 0: no output folder,
    ``.hydra`` files or log of its own (rank 0's folder is the run's, and only rank 0 writes);
    none for rank 0 or a single process. The recipes add them before Hydra reads the command
    line."""
    if distributed.is_main_process():
        return []
    return [
        "hydra.run.dir=.",
        "hydra.output_subdir=null",
        "hydra/job_logging=disabled",
        "hydra/hydra_logging=disabled",
    ]


# --- resuming ------------------------------------------------------------------------------------
# How the networks execute, not what they learn: a run may resume with other values.
EXECUTION_SETTINGS = ("bf16", "tf32", "compile", "cuda_graphs", "deterministic")
# What only sets the initial weights, which a checkpoint's weights replace.
INITIALISATION_SETTINGS = ("policy_output_gain", "initial_action_mean")


RENAMED_TRAIN_SETTINGS = {
    "value_clip_start": "clip_value_start",
    "value_clip_end": "clip_value_end",
}
"""Earlier name -> name of the training settings renamed since checkpoints were first written."""


def network_settings(model_config: dict) -> dict:
    """The model settings a checkpoint's weights depend on (``INITIALISATION_SETTINGS`` aside,
    so checkpoints from before such a setting existed still load)."""
    return {k: v for k, v in model_config.items() if k not in INITIALISATION_SETTINGS}


def check_action_mode(checkpoint: dict, scene: TerraShiftConfig, key: str) -> None:
    """Raises ``ValueError`` when the policy of ``checkpoint`` (named by the setting ``key``)
    was trained with other actions than ``scene``'s, where its actions would mean something
    else; a checkpoint older than ``action_mode`` had the paper's delta actions."""
    trained = checkpoint["env_config"].get("action_mode", "delta")
    if trained != scene.action_mode:
        raise ValueError(
            f"{key} was trained with env.action_mode={trained} and this scene has "
            f"{scene.action_mode}, where its actions mean something else; set "
            f"env.action_mode={trained}"
        )


def hydra_override(key: str, value: Any) -> str:
    """``key=value`` as Hydra reads it back as ``value``.

    Example:
        >>> print(hydra_override("env.column_shape", "box"), hydra_override("model.gain", 0.5))
        env.column_shape=box model.gain=0.5
    """
    text = json.dumps(value, separators=(",", ":"))  # null, true, [4,8,8], "box"
    if isinstance(value, str):
        try:  # unquoted where Hydra reads the bare string as that string
            if OverridesParser.create().parse_override(f"{key}={value}").value() == value:
                text = value
        except OverrideParseException:
            pass
    return f"{key}={text}"


def override(key: str, value: Any) -> str:
    """:func:`hydra_override`, quoted for a shell where needed.

    Example:
        >>> print(override("env.column_shape", "box"), override("model.cnn_channels", [8, 16]))
        env.column_shape=box 'model.cnn_channels=[8,16]'
    """
    return shlex.quote(hydra_override(key, value))


def check_resumable(resume: dict, configs: dict, cfg: DictConfig) -> None:
    """Raises unless the checkpoint ``resume`` was trained with ``configs`` (env, model, train
    and loss settings, execution and initialisation settings aside), naming the overrides that
    would continue it. A training setting saved under an earlier name
    (:data:`RENAMED_TRAIN_SETTINGS`) is compared under its name now."""
    differ = []
    configs = {**configs, "model_config": network_settings(configs["model_config"])}
    saved_train = resume["train_config"].items()
    resume = {
        **resume,
        "train_config": {RENAMED_TRAIN_SETTINGS.get(k, k): v for k, v in saved_train},
    }
    # a training setting the checkpoint predates was trained at its default
    predated = {
        "env_config": {},
        "model_config": {},
        "train_config": dataclasses.asdict(TrainConfig()),
    }
    for name, group in (("env_config", "env"), ("model_config", "model"), ("train_config", "")):
        for key, value in configs[name].items():
            saved = resume[name].get(key, predated[name].get(key))
            if saved == value or (name == "train_config" and key in EXECUTION_SETTINGS):
                continue
            differ.append(override(f"{group}.{key}" if group else setting_name(key), saved))
    if differ:
        raise ValueError(
            f"run.resume={cfg.run.resume} was trained with other settings; add "
            f"{' '.join(differ)} to continue it (or start a new run from its weights with "
            "run.pretrained)"
        )


# --- the loop's parts ----------------------------------------------------------------------------
class StopRequest:
    """SIGINT (Ctrl-C) and SIGTERM (a scheduler's kill) handler: the first signal lets the
    running iteration finish, so the checkpoint written then is a consistent one; a second
    interrupts at once, without a checkpoint. Restores the previous handlers on exit."""

    SIGNALS = (signal.SIGINT, signal.SIGTERM)

    def __init__(self, progress: tqdm) -> None:
        self.progress = progress
        self.requested = False

    def __call__(self, signum: int, frame: Any) -> None:
        if self.requested:
            raise KeyboardInterrupt
        self.requested = True
        if self.progress.disable:  # a data-parallel run's other ranks are silent
            return
        self.progress.write(
            f"{signal.Signals(signum).name}: stopping after this iteration, then saving a "
            "checkpoint to resume from (signal again to quit at once, without one)"
        )

    def __enter__(self) -> StopRequest:
        self.previous = {number: signal.signal(number, self) for number in self.SIGNALS}
        return self

    def __exit__(self, *exc_info: Any) -> None:
        for number, handler in self.previous.items():
            signal.signal(number, handler)


def make_logger(cfg: DictConfig, run_dir: Path, run_id: str | None) -> Logger | None:
    """The logger ``cfg.logger`` names, writing under ``run_dir``; ``run_id`` continues a wandb
    run."""
    kind = cfg.logger.kind
    if kind == "none":
        return None
    if kind == "csv":
        from torchrl.record.loggers import CSVLogger

        return CSVLogger(cfg.run.name, log_dir=str(run_dir / "logs"))
    if kind == "tensorboard":
        from torchrl.record.loggers import TensorboardLogger

        return TensorboardLogger(cfg.run.name, log_dir=str(run_dir / "logs"))
    from torchrl.record.loggers import WandbLogger

    return WandbLogger(
        cfg.run.name,
        offline=cfg.logger.mode == "offline",
        save_dir=str(run_dir),
        project=cfg.logger.project,
        id=run_id,
        resume="allow",
        log_env_packages=False,
    )


def checkpoint_state(
    trainer: MAPOCATrainer, configs: dict, run_id: str | None, best: dict[str, Any]
) -> dict:
    """What ``last.pt`` holds: the trainer's state, the configs, the logger's run and the best
    reward's window."""
    return {**trainer.state_dict(), **configs, "logger_run_id": run_id, "best": best}


def weights_state(trainer: MAPOCATrainer, configs: dict, **extra: Any) -> dict:
    """The networks, configs and counters: what evaluate.py and finetuning read."""
    return {
        **trainer.weights_state_dict(),
        **configs,
        "iteration": trainer.iteration,
        "env_steps": trainer.env_steps,
        **extra,
    }


def update_best(
    best: dict[str, Any],
    reward: float,
    window: int,
    trainer: MAPOCATrainer,
    configs: dict,
    path: Path,
) -> None:
    """Adds an iteration's reward per decision to ``best``'s window; when the window's mean is
    the highest yet, writes the networks and configs to ``path`` (what evaluate.py reads)."""
    best["recent"] = [*best["recent"], reward][-window:]
    mean = sum(best["recent"]) / len(best["recent"])
    if len(best["recent"]) == window and mean > best["reward"]:
        best["reward"] = mean
        save_checkpoint(weights_state(trainer, configs, mean_reward_per_decision=mean), path)


def _world_size_change(saved: int, now: int) -> str:
    """What resuming a checkpoint of ``saved`` processes with ``now`` processes does.

    Example:
        >>> _world_size_change(4, 2).split("over, ")[1]
        'the environments of ranks 0-1 continue, those of ranks 2-3 are left behind'
        >>> _world_size_change(1, 2).split("over, ")[1]
        'the environments of rank 0 continue, and new ones from run.seed + rank for rank 1'
    """

    def ranks(first: int, last: int) -> str:
        return f"rank {first}" if first == last else f"ranks {first}-{last}"

    change = (
        f"and new ones from run.seed + rank for {ranks(saved, now - 1)}"
        if now > saved
        else f"those of {ranks(now, saved - 1)} are left behind"
    )
    return (
        f"the checkpoint was trained by {saved} process(es) and continues with {now}: the "
        "weights, optimiser, return statistics and counters carry over, the environments of "
        f"{ranks(0, min(saved, now) - 1)} continue, {change}"
    )


def log_scalars(logger: Logger | None, metrics: dict[str, float], step: int) -> None:
    """Logs every metric at ``step`` (env-steps), unless there is no logger."""
    if logger is not None:
        for name, value in metrics.items():
            logger.log_scalar(name, value, step=step)


# --- the run -------------------------------------------------------------------------------------
def run_training(cfg: DictConfig, *, run_dir: Path) -> Path:
    """Trains as the pretraining and finetuning recipes' config ``cfg`` says, writing the
    checkpoints, logs and resolved config under ``run_dir``; returns the last checkpoint's path.

    Every setting is checked before anything is built; ``run.resume`` continues a run exactly,
    ``run.pretrained`` starts from a checkpoint's weights. SIGINT or SIGTERM stops after the
    running iteration with a checkpoint (:class:`StopRequest`).

    Started by ``torchrun``, each process joins the process group (unless it is in it already;
    then it stays), trains data-parallel on its own device with seed ``run.seed + rank``
    (:mod:`~terrashift_rl.training.distributed`) and leaves the group at the end; rank 0 alone
    logs, shows progress and writes files.
    """
    # --- config ------------------------------------------------------------------------------
    check_settings(cfg, RUN_SETTINGS)
    if cfg.logger.kind == "wandb":
        check_settings(cfg, {"logger.mode": one_of("offline", "online")})
    env_config = structured(TerraShiftConfig, cfg.env, "env")
    model_config = structured(TerraShiftModelConfig, cfg.model, "model")
    train_config = train_config_of(cfg)
    train_config.validate()
    window, snapshot_every = cfg.run.best_window, cfg.run.snapshot_every
    eval_every, eval_episodes = cfg.run.eval_every, cfg.run.eval_episodes
    device = resolve_device(cfg.run.device, "run.device")
    checkpoints = run_dir / "checkpoints"
    configs = {
        "env_config": dataclasses.asdict(env_config),
        "model_config": dataclasses.asdict(model_config),
    }
    resume = load_checkpoint(cfg.run.resume, required=RESUME_KEYS) if cfg.run.resume else None
    if resume is not None:
        check_resumable(resume, {**configs, "train_config": dataclasses.asdict(train_config)}, cfg)
    # a run killed while writing a checkpoint leaves its temporary file beside it
    folders = [checkpoints] if resume is None else [checkpoints, Path(cfg.run.resume).parent]
    for folder in folders if distributed.is_main_process() else []:
        for path in remove_stale_temporaries(folder):
            print(f"removed {path}, left by a checkpoint write that never finished")

    # --- setup -------------------------------------------------------------------------------
    joins = distributed.launched() and not distributed.is_distributed()
    if distributed.launched():  # one rank of torchrun's: its own device, seed and environments
        device = distributed.init_process_group(cfg.run.device, key="run.device")
    main, seed = distributed.is_main_process(), cfg.run.seed + distributed.rank()
    if not main:  # rank 0 alone evaluates and writes best.pt and snapshots
        window, snapshot_every, eval_every = 0, None, None
    torch.manual_seed(seed)
    networks = make_terrashift_networks(model_config).to(device)
    if cfg.run.pretrained:
        pretrained = load_checkpoint(cfg.run.pretrained, required=WEIGHTS_KEYS)
        if network_settings(pretrained["model_config"]) != network_settings(
            configs["model_config"]
        ):
            raise ValueError(
                f"run.pretrained={cfg.run.pretrained} holds a network of another shape; use the "
                "model settings it was trained with (the recipes do when the command line sets "
                "none)"
            )
        check_action_mode(pretrained, env_config, "run.pretrained")
    env = make_training_env(
        env_config, networks, num_envs=train_config.num_envs, device=device, seed=seed
    )
    trainer = MAPOCATrainer(env, networks, train_config)
    if cfg.run.pretrained:
        trainer.load_weights(pretrained)
    # evaluation mode (no respawn, no approach shaping), the same scenes at every evaluation
    eval_env = eval_every and make_training_env(
        evaluation_scene(env_config),
        networks,
        num_envs=eval_episodes,
        device=device,
        seed=cfg.run.eval_seed,
    )
    run_id = None
    best = {"reward": -math.inf, "recent": []}
    if resume is not None:
        trainer.load_state_dict(resume)
        run_id = resume["logger_run_id"]
        best = resume.get("best", best)
        if main and resume.get("world_size", 1) != distributed.world_size():
            print(_world_size_change(resume.get("world_size", 1), distributed.world_size()))
    logger = make_logger(cfg, run_dir, run_id) if main else None
    if logger is not None and hasattr(logger, "experiment") and run_id is None:
        run_id = getattr(logger.experiment, "id", None)
    if main:
        OmegaConf.save(cfg, run_dir / "config.yaml")

    # --- train -------------------------------------------------------------------------------
    deadline = None if cfg.run.minutes is None else time.monotonic() + 60.0 * cfg.run.minutes
    last = checkpoints / "last.pt"
    progress = tqdm(
        total=cfg.run.total_env_steps,
        initial=trainer.env_steps,
        unit="step",
        unit_scale=True,
        desc=cfg.run.name,
        dynamic_ncols=True,
        disable=not main,
    )

    def evaluate_now() -> dict[str, float]:
        return evaluate_periodically(
            eval_env, networks.actor, seed=cfg.run.eval_seed, sampled=cfg.run.eval_sampled
        )

    def save_last() -> None:
        state = checkpoint_state(trainer, configs, run_id, best)  # on every rank: a collective
        if main:
            save_checkpoint(state, last)

    goal_fraction = "-"  # the latest evaluation's goal fraction, for the progress bar
    if eval_env and cfg.run.pretrained and resume is None:  # a finetune's zero-shot score
        zero_shot = evaluate_now()
        goal_fraction = f"{zero_shot['eval_goal_fraction']:.3f}"
        progress.write(f"evaluation of the pretrained weights: {zero_shot}")
        log_scalars(logger, zero_shot, trainer.env_steps)
    try:
        with StopRequest(progress) as stop:
            for metrics in iterate_until(
                trainer, total_env_steps=cfg.run.total_env_steps, deadline=deadline
            ):
                progress.update(trainer.env_steps - progress.n)
                if eval_env and trainer.iteration % eval_every == 0:
                    metrics.update(evaluate_now())
                    goal_fraction = f"{metrics['eval_goal_fraction']:.3f}"
                progress.set_postfix(
                    eval_goals=goal_fraction,
                    reward=f"{metrics['reward_per_decision']:+.4f}",
                    steps_per_s=f"{metrics['env_steps_per_s']:,.0f}",
                )
                log_scalars(logger, metrics, trainer.env_steps)
                if window:
                    reward = metrics["reward_per_decision"]
                    update_best(best, reward, window, trainer, configs, checkpoints / "best.pt")
                if trainer.iteration % cfg.run.checkpoint_every == 0:
                    save_last()
                if snapshot_every and trainer.iteration % snapshot_every == 0:
                    snapshot = checkpoints / f"iteration_{trainer.iteration:06d}.pt"
                    save_checkpoint(weights_state(trainer, configs), snapshot)
                if distributed.any_process(stop.requested):  # every rank stops alike
                    break
            # between iterations: the state is consistent, the checkpoint resumes exactly
            save_last()
            if eval_env and trainer.iteration % eval_every:  # the final policy's score too
                final = evaluate_now()
                progress.write(f"evaluation at {trainer.env_steps:,} env-steps: {final}")
                log_scalars(logger, final, trainer.env_steps)
    except KeyboardInterrupt:
        if main:
            progress.write(f"interrupted mid-iteration; {last} is the last checkpoint written")
        raise SystemExit(130) from None
    except FloatingPointError as error:
        if not main:  # every rank stops at the same iteration; rank 0 says why
            raise SystemExit(1) from None
        written = f"{last} is the last checkpoint written" if last.exists() else "no checkpoint"
        raise SystemExit(f"{error}\nstopped without saving that iteration; {written}") from None
    finally:  # cleanup
        progress.close()
        if (
            logger is not None
            and hasattr(logger, "experiment")
            and hasattr(logger.experiment, "finish")
        ):
            logger.experiment.finish()
        if joins:  # leaves the process group as it found it
            distributed.destroy_process_group()
    if main:
        print(
            f"{trainer.env_steps:,} env-steps in {trainer.iteration} iterations; checkpoint {last}"
        )
    return last
