"""How a recipe meets its command line and its machine: the device setting, Warp's start on it,
the CPU-sized defaults of a run without CUDA, the run's folder and the command that resumes it,
and the command line of a ``torchrun`` rank other than 0."""

from __future__ import annotations

import logging
import os
import shlex
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch
import warp as wp
from hydra import compose
from hydra.core.hydra_config import HydraConfig
from hydra.core.override_parser.overrides_parser import OverridesParser
from hydra.errors import OverrideParseException
from omegaconf import DictConfig, ListConfig, OmegaConf

from terrashift_rl.fields import check_value
from terrashift_rl.training import distributed
from terrashift_rl.training.checkpoint import load_checkpoint
from terrashift_rl.training.settings import OVERRIDES, hydra_override

__all__ = [
    "cpu_overrides",
    "hydra_overrides_of_other_ranks",
    "register_run_folder",
    "resolve_device",
    "resume_command",
    "run_folder",
    "shown",
    "size_for_the_machine",
    "start_warp",
]

log = logging.getLogger(__name__)


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


def start_warp(device: torch.device) -> None:
    """Initialises Warp for the run's ``device``. On the CPU its native library's start is kept
    off the terminal: it would print that it found no CUDA driver, which the run has said
    already (a Python error of Warp's start still raises)."""
    if device.type != "cpu":
        wp.init()
        return
    sys.stderr.flush()
    terminal, nothing = os.dup(2), os.open(os.devnull, os.O_WRONLY)
    os.dup2(nothing, 2)
    try:
        wp.init()
    finally:
        os.dup2(terminal, 2)
        os.close(terminal)
        os.close(nothing)


def run_folder(resume: str | None, fresh: str) -> str:
    """Hydra's run folder (``hydra.run.dir``, the resolver ``${run_folder:...}`` of the training
    configs): the folder of the run whose ``<run>/checkpoints/last.pt`` ``resume`` names, so
    that a resumed run goes on writing there and its ``last.pt`` stays where it was; ``fresh``
    for a new run or a checkpoint kept elsewhere.

    Example:
        >>> run_folder("outputs/2026-11-27/08-00-00/checkpoints/last.pt", "outputs/new")
        'outputs/2026-11-27/08-00-00'
        >>> run_folder(None, "outputs/new"), run_folder("saved/last.pt", "outputs/new")
        ('outputs/new', 'outputs/new')
    """
    path = Path(resume) if resume else None
    if path is None or path.name != "last.pt" or path.parent.name != "checkpoints":
        return fresh
    return str(path.parent.parent)


def register_run_folder() -> None:
    """Lets the configs name :func:`run_folder` as ``${run_folder:<resume>,<fresh folder>}``."""
    OmegaConf.register_new_resolver("run_folder", run_folder, replace=True)


def resume_command(checkpoint: Path) -> str:
    """The command that resumes this run from ``checkpoint``: the recipe, its config name where
    the command line gave one and every override of the command line, with ``run.resume``
    (relative to the working folder where it lies below it). Needs Hydra's app context."""
    hydra_config = HydraConfig.get()
    script = sys.argv[0]
    words = ["python", script]
    if hydra_config.job.config_name != Path(script).stem:
        words += ["--config-name", hydra_config.job.config_name]
    given = list(hydra_config.overrides.task)
    words += [text for text, key in zip(given, _keys(given), strict=True) if key != "run.resume"]
    words.append(f"run.resume={shown(checkpoint)}")
    return shlex.join(words)


def shown(path: Path) -> Path:
    """``path`` as a message shows it: relative to the working folder where it lies below it."""
    path = Path(path).absolute()
    return path.relative_to(Path.cwd()) if path.is_relative_to(Path.cwd()) else path


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
    defaults = OmegaConf.select(cfg, defaults_key)
    if isinstance(defaults, ListConfig):
        defaults = OmegaConf.to_container(defaults)
    check_value(defaults_key, defaults, list[str], OVERRIDES)
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
        try:
            sized = cpu_overrides(defaults, [*pinned, *given])
        except OverrideParseException as error:
            raise ValueError(
                f"{defaults_key}={defaults} holds an override Hydra cannot read: {error}"
            ) from None
        note = f" with the model of {source}" if pinned else ""
        if distributed.is_main_process():
            log.info(
                f"no CUDA device: a CPU-sized run ({' '.join(sized)}){note}; set {device_key}=cpu "
                "to keep the configured sizes"
                if sized
                else f"no CUDA device: running on the CPU with the configured sizes{note}"
            )
    elif changed and distributed.is_main_process():
        log.info(
            f"the model of {source}: it differs from the configured one in {', '.join(changed)}"
        )
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
