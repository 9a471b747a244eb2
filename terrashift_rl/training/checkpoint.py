"""What a checkpoint holds and must match, written atomically and loaded without running code.

A checkpoint holds the weights, configs and counters that evaluation and finetuning read
(:data:`WEIGHTS_KEYS`, :func:`weights_state`); ``last.pt`` also the trainer's whole state, the
logger's run and the best reward's window (:data:`RESUME_KEYS`, :func:`last_state`).
:func:`check_resumable` says whether a run's settings continue a checkpoint, and
:func:`check_action_mode` whether a policy's actions mean the same in a scene. Every loaded
checkpoint passes :func:`upgrade`, the one converter of checkpoints written before the current
layout.

A run killed mid-write keeps the previous checkpoint. Loading uses ``torch.load`` with
``weights_only=True``: a checkpoint may hold tensors, numbers, strings, lists and dicts, nothing
that unpickling would have to construct by calling Python code, so a shared file cannot run
anything. Tensordicts (the trainer's carried state, also inside the lists and dicts of a
data-parallel run's per-rank states) are stored as nested dicts of tensors with their batch sizes
and rebuilt on loading.
"""

from __future__ import annotations

import dataclasses
import math
import os
import pickle
import re
import tempfile
import time
import zipfile
from collections.abc import Iterable
from pathlib import Path
from typing import TYPE_CHECKING, Any

import torch
from tensordict import TensorDict, TensorDictBase

from terrashift_rl.sim import TerraShiftConfig
from terrashift_rl.training.algorithms import ALGORITHMS
from terrashift_rl.training.settings import CurriculumSettings, TrainConfig, override

if TYPE_CHECKING:
    from terrashift_rl.training.trainer import OnPolicyTrainer

WEIGHTS_KEYS = ("networks", "env_config", "model_config", "env_steps")
"""What evaluate.py and finetuning read (:func:`weights_state`)."""
RESUME_KEYS = (*WEIGHTS_KEYS, "optimizer", "train_config", "simulator", "carry")
"""What resuming reads besides (:func:`last_state`)."""
EXECUTION_SETTINGS = ("bf16", "tf32", "compile", "cuda_graphs", "deterministic")
"""Training settings of how the networks execute, not what they learn: a run may resume with
other values."""
INITIALISATION_SETTINGS = ("initial_action_mean",)
"""Model settings that only set the initial weights, which a checkpoint's weights replace."""
RETIRED_SETTINGS = {"model_config": ("policy_output_gain",)}
"""Settings that earlier checkpoints hold and that are no longer settings (they only set
initial weights, so a checkpoint's weights do not depend on them)."""

_TENSORDICT = "__tensordict__"
"""Marks a tensordict stored as plain tensors: ``{_TENSORDICT: {batch_size, entries}}``."""

CONVERT_COMMAND = (
    'python -c "import sys, torch; from terrashift_rl.training import save_checkpoint; '
    'save_checkpoint(torch.load(sys.argv[1], weights_only=False), sys.argv[1])" <file>'
)
"""Rewrites a checkpoint of an earlier version (a pickled tensordict) that one trusts."""

STALE_AFTER_S = 60.0
"""A temporary file untouched this long is left by a write that never finished: a write in
progress keeps its file fresh."""


def save_checkpoint(state: dict[str, Any], path: str | Path) -> Path:
    """Writes ``state`` with ``torch.save`` to a temporary file beside ``path``, flushes it to
    disk, then renames it over ``path`` (an atomic replace on POSIX file systems).

    Example:
        >>> import tempfile
        >>> from tensordict import TensorDict
        >>> carry = TensorDict({"x": torch.arange(3)}, batch_size=[3])
        >>> with tempfile.TemporaryDirectory() as folder:
        ...     path = save_checkpoint({"step": 1, "carry": carry}, f"{folder}/last.pt")
        ...     loaded = load_checkpoint(path, required=("step",))
        >>> loaded["step"], loaded["carry"]["x"].tolist(), loaded["carry"].batch_size
        (1, [0, 1, 2], torch.Size([3]))
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    handle, temporary = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(handle, "wb") as file:
            torch.save({key: _plain(value) for key, value in state.items()}, file)
            file.flush()
            os.fsync(file.fileno())
        os.chmod(temporary, 0o644)  # mkstemp creates owner-only files
        os.replace(temporary, path)
    except BaseException:
        Path(temporary).unlink(missing_ok=True)
        raise
    return path


def load_checkpoint(
    path: str | Path,
    *,
    required: Iterable[str] = (),
    map_location: str | torch.device = "cpu",
) -> dict:
    """Loads a checkpoint written by :func:`save_checkpoint`.

    Raises ``FileNotFoundError`` when ``path`` does not exist and ``ValueError`` naming it when it
    is empty, truncated, corrupt, not a checkpoint, lacks one of the ``required`` entries, or
    holds Python objects whose loading would run code (refused: nothing in the file runs).
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no checkpoint at {path}")
    try:
        with zipfile.ZipFile(path) as archive:
            damaged = archive.testzip()  # reads every record against its CRC
    except zipfile.BadZipFile:
        raise ValueError(
            f"checkpoint {path} ({path.stat().st_size:,} bytes) is not a zip archive as "
            "torch.save writes: it is truncated, corrupt or another kind of file"
        ) from None
    if damaged is not None:
        raise ValueError(f"checkpoint {path} is corrupt: its record {damaged} fails its CRC check")
    try:
        state = torch.load(path, map_location=map_location, weights_only=True)
    except Exception as error:  # torch.load's errors vary with what the archive holds
        raise ValueError(_why_unreadable(path, error)) from None
    if not isinstance(state, dict):
        raise ValueError(f"{path} holds a {type(state).__name__}, not a checkpoint (a dict)")
    missing = [key for key in required if key not in state]
    if missing:
        raise ValueError(f"checkpoint {path} lacks {missing}; it holds {list(state)}")
    return upgrade({key: _rebuilt(value) for key, value in state.items()})


_RENAMED = {"value_clip_start": "clip_value_start", "value_clip_end": "clip_value_end"}


def upgrade(state: dict[str, Any]) -> dict[str, Any]:
    """A checkpoint in the current layout, from one written by an earlier version: the one
    converter of old checkpoints, applied to every loaded one (a current one passes unchanged).

    - ``algo`` and ``algorithm_networks``: absent before the algorithms existed, MA-POCA's.
    - ``env_config.action_mode``: absent before action modes existed, the paper's ``delta``.
    - ``train_config``: one flat dict before the loss settings became the algorithm's own; its
      loss settings move to ``train_config["loss"]``, those renamed since (``value_clip_*``)
      take their names now, and a setting the checkpoint predates takes its default then.
    - ``best``: absent before ``best.pt`` existed, an empty window.
    - :data:`RETIRED_SETTINGS` are dropped.

    Example:
        >>> old = {"networks": {}, "env_config": {}, "train_config": {"value_clip_start": 0.2}}
        >>> new = upgrade(old)
        >>> new["algo"], new["env_config"]["action_mode"], new["train_config"]["loss"]["gamma"]
        ('mapoca', 'delta', 0.95)
        >>> new["train_config"]["loss"]["clip_value_start"]
        0.2
    """
    if "networks" not in state:  # not a training checkpoint
        return state
    state = dict(state)
    train = state.get("train_config")
    algo = state.setdefault("algo", (train or {}).get("algo", "mapoca"))
    state.setdefault("algorithm_networks", {})
    if "env_config" in state:
        state["env_config"] = {"action_mode": "delta", **state["env_config"]}
    if "optimizer" in state:
        state.setdefault("best", {"reward": -math.inf, "recent": []})
    for name, retired in RETIRED_SETTINGS.items():
        if name in state:
            state[name] = {key: value for key, value in state[name].items() if key not in retired}
    if train is not None and "loss" not in train:
        flat = {_RENAMED.get(key, key): value for key, value in train.items() if key != "algo"}
        defaults = dataclasses.asdict(TrainConfig(loss=ALGORITHMS[algo]()))
        state["train_config"] = {
            **{key: flat.get(key, value) for key, value in defaults.items() if key != "loss"},
            "loss": {key: flat.get(key, value) for key, value in defaults["loss"].items()},
        }
    return state


# --- what a checkpoint holds and must match -------------------------------------------------------
def weights_state(trainer: OnPolicyTrainer, configs: dict, **extra: Any) -> dict:
    """The networks, configs and counters: what evaluate.py and finetuning read."""
    return {
        **trainer.weights_state_dict(),
        **configs,
        "iteration": trainer.iteration,
        "env_steps": trainer.env_steps,
        **extra,
    }


def last_state(
    trainer: OnPolicyTrainer, configs: dict, run_id: str | None, best: dict[str, Any]
) -> dict:
    """What ``last.pt`` holds: the trainer's state, the configs, the logger's run and the best
    reward's window. In a data-parallel run every rank calls it (a collective)."""
    return {**trainer.state_dict(), **configs, "logger_run_id": run_id, "best": best}


def update_best(
    best: dict[str, Any],
    reward: float,
    window: int,
    trainer: OnPolicyTrainer,
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


def network_settings(model_config: dict) -> dict:
    """The model settings a checkpoint's weights depend on (``INITIALISATION_SETTINGS`` aside)."""
    return {k: v for k, v in model_config.items() if k not in INITIALISATION_SETTINGS}


def check_action_mode(checkpoint: dict, scene: TerraShiftConfig, key: str) -> None:
    """Raises ``ValueError`` when the policy of ``checkpoint`` (named by the setting ``key``)
    was trained with other actions than ``scene``'s, where its actions would mean something
    else."""
    trained = checkpoint["env_config"]["action_mode"]
    if trained != scene.action_mode:
        raise ValueError(
            f"{key} was trained with env.action_mode={trained} and this scene has "
            f"{scene.action_mode}, where its actions mean something else; set "
            f"env.action_mode={trained}"
        )


def check_resumable(resume: dict, configs: dict, *, path: str | Path) -> None:
    """Raises unless the checkpoint ``resume`` (at ``path``) was trained with ``configs``
    (``env_config``, ``model_config``, ``train_config``, ``curriculum_config``: env, model,
    train, loss and curriculum settings, execution and initialisation settings aside), naming
    the overrides that would continue it. A checkpoint from before the curriculum was trained
    without one."""
    differ = []
    train, saved_train = dict(configs["train_config"]), dict(resume["train_config"])
    loss, saved_loss = train.pop("loss"), saved_train.pop("loss")
    if resume["algo"] != configs["algo"]:
        differ.append(f"algo={resume['algo']}")
        loss = saved_loss  # the other algorithm's settings are compared once it is set
    for group, now, saved in (
        ("env", configs["env_config"], resume["env_config"]),
        ("model", network_settings(configs["model_config"]), resume["model_config"]),
        ("train", train, saved_train),
        ("loss", loss, saved_loss),
        (
            "curriculum",
            configs["curriculum_config"],
            resume.get("curriculum_config", dataclasses.asdict(CurriculumSettings())),
        ),
    ):
        for key, value in now.items():
            if saved.get(key) != value and key not in EXECUTION_SETTINGS:
                differ.append(override(f"{group}.{key}", saved.get(key)))
    if differ:
        raise ValueError(
            f"run.resume={path} was trained with other settings; add {' '.join(differ)} to "
            "continue it (or start a new run from its weights with run.pretrained)"
        )


def world_size_change(saved: int, now: int) -> str:
    """What resuming a checkpoint of ``saved`` processes with ``now`` processes does.

    Example:
        >>> world_size_change(4, 2).split("over, ")[1]
        'the environments of ranks 0-1 continue, those of ranks 2-3 are left behind'
        >>> world_size_change(1, 2).split("over, ")[1]
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


def remove_stale_temporaries(folder: str | Path) -> list[Path]:
    """Removes the temporary files that :func:`save_checkpoint` left in ``folder`` when killed
    mid-write (those untouched for ``STALE_AFTER_S``); returns their paths."""
    stale = [
        path
        for path in Path(folder).glob(".*.tmp")
        if time.time() - path.stat().st_mtime > STALE_AFTER_S
    ]
    for path in stale:
        path.unlink(missing_ok=True)
    return stale


def _why_unreadable(path: Path, error: Exception) -> str:
    message = str(error)
    if not (isinstance(error, pickle.UnpicklingError) and "Weights only load failed" in message):
        return f"checkpoint {path} is not a PyTorch archive ({type(error).__name__}: {message})"
    named = re.search(r"GLOBAL ([\w.]+)", message)
    would = f"call {named[1]}" if named else "run pickle instructions that plain data never needs"
    return (
        f"refused to load {path}: loading it would {would}, and a checkpoint must not run code; "
        "checkpoints hold only tensors, numbers, strings, lists and dicts. A checkpoint written "
        f"by an earlier version of terrashift_rl, if you trust it, converts once with: "
        f"{CONVERT_COMMAND}"
    )


def _plain(value: Any) -> Any:
    if isinstance(value, dict):
        return {key: _plain(entry) for key, entry in value.items()}
    if isinstance(value, list):
        return [_plain(entry) for entry in value]
    if not isinstance(value, TensorDictBase):
        return value
    return {
        _TENSORDICT: {
            "batch_size": list(value.batch_size),
            "entries": {key: _plain(entry) for key, entry in value.items()},
        }
    }


def _rebuilt(value: Any) -> Any:
    if isinstance(value, list):
        return [_rebuilt(entry) for entry in value]
    if not isinstance(value, dict):
        return value
    if _TENSORDICT not in value:
        return {key: _rebuilt(entry) for key, entry in value.items()}
    stored = value[_TENSORDICT]
    return TensorDict(
        {key: _rebuilt(entry) for key, entry in stored["entries"].items()},
        batch_size=stored["batch_size"],
    )
