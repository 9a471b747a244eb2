"""How a recipe meets its command line and its machine: the device setting, Warp's start on it,
the CPU-sized defaults of a run without CUDA, the run's folder (its lock and writability) and the
command that resumes it, the command line of a ``torchrun`` rank other than 0, Warp's kernel
cache, Inductor's compile workers at the end, and refusals that end a run with their message
alone."""

from __future__ import annotations

import fcntl
import logging
import os
import shlex
import sys
import tempfile
import threading
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
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
from terrashift_rl.training.settings import OVERRIDES

__all__ = [
    "LOCK_NAME",
    "check_warp_cache",
    "check_writable",
    "claim_run_folder",
    "close_compile_workers",
    "cpu_overrides",
    "hydra_overrides_of_other_ranks",
    "register_run_folder",
    "resolve_device",
    "refusals_end_the_run",
    "resume_command",
    "run_folder",
    "shown",
    "size_for_the_machine",
    "start_warp",
]

COMPILE_WORKERS_TIMEOUT = 10.0
"""Seconds that :func:`close_compile_workers` gives Inductor's compile workers to exit."""

LOCK_NAME = "run.lock"
"""The file in a run folder that holds the process id of the run writing there."""

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
    already (a Python error of Warp's start still raises). Says so when Warp's kernel cache
    holds none of the simulator's kernels yet (a first run on the machine, or with this Warp
    version): the first environment then waits while Warp compiles them, silently."""
    if device.type != "cpu":
        wp.init()
    else:
        sys.stderr.flush()
        terminal, nothing = os.dup(2), os.open(os.devnull, os.O_WRONLY)
        os.dup2(nothing, 2)
        try:
            wp.init()
        finally:
            os.dup2(terminal, 2)
            os.close(terminal)
            os.close(nothing)
    cache = Path(wp.config.kernel_cache_dir)
    if distributed.is_main_process() and not any(cache.glob("*terrashift_rl*")):
        log.info(
            f"Warp compiles the simulator's kernels into {cache} before the first step, once "
            "(on two CPU cores about 10 s; later runs load them)"
        )


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


def cpu_overrides(
    defaults: Sequence[str], given: Sequence[str], *, taken: Sequence[str] = ()
) -> list[str]:
    """The overrides of ``defaults`` that the command line's overrides ``given`` and the keys or
    groups ``taken`` (set another way) leave alone: a default is dropped when a given override
    sets its key, a key inside it (``model.embed_dim`` for ``model=small``) or the config group
    it lies in (``train=throughput`` for ``train.num_envs=32``).

    Example:
        >>> defaults = ["model=small", "train.num_envs=32", "run.eval_episodes=16"]
        >>> cpu_overrides(defaults, ["env=finetune", "run.seed=3"])
        ['model=small', 'train.num_envs=32', 'run.eval_episodes=16']
        >>> cpu_overrides(defaults, ["model.embed_dim=64", "train=throughput"])
        ['run.eval_episodes=16']
        >>> cpu_overrides(defaults, [], taken=["model"])
        ['train.num_envs=32', 'run.eval_episodes=16']
    """
    given_keys = [*_keys(given), *taken]
    return [
        default
        for default, key in zip(defaults, _keys(defaults), strict=True)
        if not any(_overlaps(key, other) for other in given_keys)
    ]


def _overlaps(key: str, other: str) -> bool:
    """Whether setting ``key`` and ``other`` change a common setting (one holds the other)."""
    return key == other or key.startswith(f"{other}.") or other.startswith(f"{key}.")


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
    model, changed = {}, []
    if source is not None:  # checked through the settings room; data, never parsed
        saved = load_checkpoint(OmegaConf.select(cfg, source), required=("model_config",))
        given_keys = _keys(given)
        model = {
            key: value
            for key, value in saved["model_config"].items()
            if not any(_overlaps(f"model.{key}", other) for other in given_keys)
        }
        changed = [key for key, value in model.items() if cfg.model[key] != value]
    sized = []
    if sizing:
        try:
            sized = cpu_overrides(defaults, given, taken=["model"] if model else [])
        except OverrideParseException as error:
            raise ValueError(
                f"{defaults_key}={defaults} holds an override Hydra cannot read: {error}"
            ) from None
        note = f" with the model of {source}" if model else ""
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
    if sized:
        cfg = compose(config_name=hydra_config.job.config_name, overrides=[*sized, *given])
    for key, value in model.items():  # the room allows no interpolation in a model setting
        cfg.model[key] = value
    return cfg


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


@contextmanager
def claim_run_folder(run_dir: str | Path) -> Iterator[None]:
    """Holds ``run_dir`` for this run while the block runs: checks that it and its
    ``checkpoints`` folder are writable (:func:`check_writable`), then takes an exclusive lock
    (``flock``) on ``run_dir/run.lock`` and writes this process's id into it; the file goes at
    the end. A folder whose lock another live run holds is refused naming that run's process.
    The system drops a lock with its process, so a run that was killed (``kill -9`` included)
    leaves a file that the next run takes over. In a data-parallel run only rank 0 writes, so
    only rank 0 claims the folder."""
    if not distributed.is_main_process():
        yield
        return
    run_dir = Path(run_dir)
    check_writable(run_dir, "the run folder")
    check_writable(run_dir / "checkpoints", "the checkpoints folder")
    lock = run_dir / LOCK_NAME
    while True:
        handle = os.open(lock, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.read(handle, 32).decode(errors="replace").strip() or "unknown"
            os.close(handle)
            raise ValueError(
                f"the run folder {run_dir} is in use by the run of process {holder} (it holds "
                f"{LOCK_NAME}); wait for it to end or write elsewhere (hydra.run.dir=<folder>)"
            ) from None
        if lock.exists() and os.stat(lock).st_ino == os.fstat(handle).st_ino:
            break
        os.close(handle)  # the file was removed by the run that held it: lock its successor
    try:
        os.ftruncate(handle, 0)
        os.write(handle, str(os.getpid()).encode())
        yield
    finally:
        lock.unlink(missing_ok=True)  # while still locked, so no run locks a removed file
        os.close(handle)


def check_writable(folder: str | Path, role: str) -> None:
    """Creates ``folder`` if needed and writes and removes a file in it; raises ``ValueError``
    naming it by its ``role`` and the system's reason when either fails.

    Example:
        >>> check_writable("/proc/no", "the run folder")
        Traceback (most recent call last):
        ...
        ValueError: the run folder /proc/no cannot be written (No such file or directory)
    """
    folder = Path(folder)
    try:
        folder.mkdir(parents=True, exist_ok=True)
        with tempfile.NamedTemporaryFile(dir=folder, prefix=".writable."):
            pass
    except OSError as error:
        raise ValueError(f"{role} {folder} cannot be written ({error.strerror or error})") from None


def check_warp_cache() -> None:
    """Raises ``ValueError`` naming ``WARP_CACHE_PATH`` when it is set to a folder where Warp
    cannot keep its compiled kernels."""
    path = os.environ.get("WARP_CACHE_PATH")
    if path is not None:
        try:
            check_writable(path, "WARP_CACHE_PATH, Warp's kernel cache, at")
        except ValueError as error:
            raise ValueError(f"{error}; set it to a writable folder or unset it") from None


def close_compile_workers(timeout: float = COMPILE_WORKERS_TIMEOUT) -> bool:
    """Shuts down the worker pools that ``torch.compile`` started, killing any still running
    after ``timeout`` seconds; returns whether all of them exited on their own.

    Inductor shuts them down itself at exit, waiting up to 300 s for each, and its pool does
    not always exit (pytorch/pytorch#162199): a process that had compiled then sat for minutes
    after its last line. Nothing is waited for where nothing was compiled."""
    async_compile = sys.modules.get("torch._inductor.async_compile")
    pools = list(getattr(async_compile, "_pool_set", ()))
    if not pools:
        return True
    # Inductor's own shutdown, in a thread that can be left waiting: a pool shut down here is
    # not waited for again at exit
    closing = threading.Thread(target=async_compile.shutdown_compile_workers, daemon=True)
    closing.start()
    closing.join(timeout)
    if not closing.is_alive():
        return True
    for pool in pools:
        process = getattr(pool, "process", None)  # a SubprocPool's sidecar process
        if process is not None and process.poll() is None:
            process.kill()
    closing.join(5.0)
    log.warning(
        f"Inductor's compile workers had not exited {timeout:g} s after the run: stopped "
        "without them (pytorch/pytorch#162199)"
    )
    return False


@contextmanager
def refusals_end_the_run() -> Iterator[None]:
    """Ends the process with exit status 1 and the message alone, without a traceback, when the
    block refuses what it was given (a ``ValueError``: a setting, a checkpoint, a run folder)
    or cannot write or read a file (an ``OSError``, which names it); with exit status 130 and
    the line ``interrupted`` when Ctrl-C reaches it (one during a run's set-up, before the
    run's own handler takes over, or during an evaluation). ``HYDRA_FULL_ERROR=1`` keeps the
    traceback, as Hydra's own errors do."""
    try:
        yield
    except (ValueError, OSError, KeyboardInterrupt) as error:
        if os.environ.get("HYDRA_FULL_ERROR") == "1":
            raise
        if isinstance(error, KeyboardInterrupt):
            log.info("interrupted")
            raise SystemExit(130) from None
        raise SystemExit(f"error: {error}") from None
