"""How a recipe meets its command line and its machine: the device setting, the CPU-sized
defaults of a run without CUDA and the command line of a ``torchrun`` rank other than 0."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import torch
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
    "resolve_device",
    "size_for_the_machine",
]


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
