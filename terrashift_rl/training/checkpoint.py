"""What a checkpoint holds and must match, written atomically and loaded without running code.

A checkpoint holds the weights, configs and counters that evaluation and finetuning read
(:data:`WEIGHTS_KEYS`, :func:`weights_state`); ``last.pt`` also the trainer's whole state, the
logger's run, the best reward's window and the seconds spent in the training loop
(:data:`RESUME_KEYS`, :func:`last_state`).
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

from terrashift_rl.fields import build, shown
from terrashift_rl.modules import TerraShiftModelConfig, make_terrashift_networks
from terrashift_rl.sim import TerraShiftConfig
from terrashift_rl.training.algorithms import ALGORITHMS
from terrashift_rl.training.settings import (
    CurriculumSettings,
    TrainConfig,
    check_loss_range,
    check_network_size,
    check_reward_range,
    override,
)

if TYPE_CHECKING:
    from terrashift_rl.training.trainer import OnPolicyTrainer

WEIGHTS_KEYS = ("networks", "env_config", "model_config", "env_steps")
"""What evaluate.py and finetuning read (:func:`weights_state`)."""
RESUME_KEYS = (
    *WEIGHTS_KEYS,
    "optimizer",
    "train_config",
    "simulator",
    "carry",
    "logger_run_id",
)
"""What resuming reads besides (:func:`last_state`)."""
EXECUTION_SETTINGS = ("bf16", "tf32", "compile", "cuda_graphs", "deterministic")
"""Training settings of how the networks execute, not what they learn: a run may resume with
other values."""
SCORING_SETTINGS = ("retention_every",)
"""Curriculum settings of what a run scores, not what it learns (as the run group's
evaluations): a run may resume with other values."""
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

MAX_DEPTH = 32
"""How deep a checkpoint's lists and dicts may nest (a data-parallel ``last.pt`` nests about
eight deep)."""
MAX_ENTRIES = 1_000_000
"""How many entries a checkpoint's lists and dicts may hold together."""
ENTRIES = {
    "networks": (dict,),
    "algorithm_networks": (dict,),
    "algo": (str,),
    "env_config": (dict,),
    "model_config": (dict,),
    "train_config": (dict,),
    "curriculum_config": (dict,),
    "curriculum": (dict,),
    "iteration": (int,),
    "env_steps": (int,),
    "schedule_start": (int,),
    "mean_reward_per_decision": (float,),
    "optimizer": (dict,),
    "value_normalizer": (dict, type(None)),
    "torch_rng": (torch.Tensor,),
    "cuda_rng": (list, type(None)),
    "simulator": (dict,),
    "carry": (TensorDictBase, type(None)),
    "logger_run_id": (str, type(None)),
    "best": (dict,),
    "run_seconds": (float,),
    "world_size": (int,),
    "rank_states": (list,),
}
"""Every entry a training checkpoint may hold, with its kinds."""

STALE_AFTER_S = 60.0
"""A temporary file untouched this long is left by a write that never finished: a write in
progress keeps its file fresh."""


def save_checkpoint(state: dict[str, Any], path: str | Path) -> Path:
    """Writes ``state`` with ``torch.save`` to a temporary file beside ``path``, flushes it to
    disk, then renames it over ``path`` (an atomic replace on POSIX file systems). A write that
    fails (a full disk, a read-only folder) removes its temporary file, leaves ``path`` as it
    was and raises ``OSError`` naming ``path`` and the reason.

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
    temporary = None
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        handle, temporary = tempfile.mkstemp(
            dir=path.parent, prefix=f".{path.name}.", suffix=".tmp"
        )
        with os.fdopen(handle, "wb") as file:
            torch.save({key: _plain(value) for key, value in state.items()}, file)
            file.flush()
            os.fsync(file.fileno())
        os.chmod(temporary, 0o644)  # mkstemp creates owner-only files
        os.replace(temporary, path)
    except BaseException as error:
        if temporary is not None:
            Path(temporary).unlink(missing_ok=True)
        if not isinstance(error, OSError):
            raise
        kept = "the previous one is kept" if path.exists() else "there is no earlier one"
        reason = error.strerror or error
        raise OSError(f"checkpoint {path} could not be written ({reason}); {kept}") from None
    return path


def load_checkpoint(
    path: str | Path,
    *,
    required: Iterable[str] = (),
    map_location: str | torch.device = "cpu",
) -> dict:
    """Loads a checkpoint written by :func:`save_checkpoint`, as data: nothing in it runs or is
    parsed.

    Raises ``FileNotFoundError`` when ``path`` does not exist and ``ValueError`` naming it when it
    is empty, truncated, corrupt, not a checkpoint, larger than this machine's memory, nested
    deeper than :data:`MAX_DEPTH` or holding more than :data:`MAX_ENTRIES` entries, lacks one of
    the ``required`` entries, or holds Python objects whose loading would run code (refused:
    nothing in the file runs). A training checkpoint (one with ``networks``) is also checked
    entry by entry (:func:`check_training_state`), its configs through the settings room.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no checkpoint at {path}")
    try:
        with zipfile.ZipFile(path) as archive:
            size, memory = sum(record.file_size for record in archive.infolist()), _memory_bytes()
            if size > memory:
                raise ValueError(
                    f"checkpoint {path} unpacks to {size:,} bytes, more than this machine's "
                    f"memory ({memory:,} bytes)"
                )
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
    _check_nesting(state, path)
    missing = [key for key in required if key not in state]
    if missing:
        raise ValueError(f"checkpoint {path} lacks {missing}; it holds {list(state)[:20]}")
    state = {key: _rebuilt(value, path, key) for key, value in state.items()}
    if "networks" not in state:  # not a training checkpoint
        return state
    return check_training_state(state, path)


def check_training_state(state: dict[str, Any], path: str | Path) -> dict[str, Any]:
    """A training checkpoint's ``state`` (loaded from ``path``) in the current layout
    (:func:`upgrade`), each entry checked before anything is built from it: every entry one of
    :data:`ENTRIES` and of its kind; the configs through the settings room, as the command
    line's are (types, ranges, known keys, the network's size, the reward's and the loss's
    range), given back as the settings classes write them; the weights of ``networks`` with the
    names and shapes of the network that ``model_config`` builds; every floating-point tensor of
    the weights, the optimiser and the return statistics finite. Raises one ``ValueError``
    naming ``path``, the entry and what it must be."""
    for key, value in state.items():
        kinds = ENTRIES.get(key)
        if kinds is None:
            raise _refused(
                path,
                shown(key),
                f"is not an entry of a checkpoint; those are: {', '.join(ENTRIES)}",
            )
        if not isinstance(value, kinds):
            expected = " or ".join(
                "None" if kind is type(None) else kind.__name__ for kind in kinds
            )
            raise _refused(path, key, f"must be a {expected}, got a {type(value).__name__}")
    for key in _SETTINGS:
        entries = state.get(key, {})
        if any(not isinstance(name, str) for name in entries):
            raise _refused(path, key, "must be a mapping of setting names to values")
    train = state.get("train_config", {})
    for entry, algo in (("algo", state.get("algo")), ("train_config['algo']", train.get("algo"))):
        if algo is not None and not (isinstance(algo, str) and algo in ALGORITHMS):
            raise _refused(
                path, entry, f"must be one of {', '.join(ALGORITHMS)}, got {shown(algo)}"
            )
    best = state.get("best", {"reward": 0.0, "recent": []})
    if not (
        set(best) == {"reward", "recent"}
        and isinstance(best["reward"], float)
        and isinstance(best["recent"], list)
        and all(isinstance(reward, float) for reward in best["recent"])
    ):
        raise _refused(path, "best", "must be {'reward': a number, 'recent': [numbers]}")
    state = upgrade(state)
    settings = {}
    for key, check in _SETTINGS.items():
        if key in state:
            try:
                settings[key] = check(state[key], state["algo"])
            except ValueError as error:
                raise _refused(path, key, str(error)) from None
    if "train_config" in settings and "env_config" in settings:
        try:
            check_loss_range(settings["train_config"], settings["env_config"])
        except ValueError as error:
            raise _refused(path, "train_config", str(error)) from None
    state.update({key: dataclasses.asdict(value) for key, value in settings.items()})
    if "model_config" in settings:
        _check_weights(state["networks"], settings["model_config"], path)
    for key in ("algorithm_networks", "optimizer", "value_normalizer"):
        _check_finite(state.get(key), path, key)
    return state


def _env_settings(values: dict, algo: str) -> TerraShiftConfig:
    env = build(TerraShiftConfig, values, "env")
    check_reward_range(env)
    return env


def _model_settings(values: dict, algo: str) -> TerraShiftModelConfig:
    model = build(TerraShiftModelConfig, values, "model")
    check_network_size(model)
    return model


def _train_settings(values: dict, algo: str) -> TrainConfig:
    values = dict(values)
    loss = values.pop("loss", {})
    if not isinstance(loss, dict):
        raise ValueError(f"train.loss must be a mapping of settings, got {shown(loss)}")
    return TrainConfig.of(values, {**loss, "algo": algo})


_SETTINGS = {
    "env_config": _env_settings,
    "model_config": _model_settings,
    "train_config": _train_settings,
    "curriculum_config": lambda values, _: build(CurriculumSettings, values, "curriculum"),
}
"""How each config a checkpoint holds passes the settings room (given the algorithm)."""


def _check_weights(weights: dict, model: TerraShiftModelConfig, path: str | Path) -> None:
    """``weights`` against the network ``model`` builds (on the meta device: nothing allocated)."""
    with torch.device("meta"):
        expected = make_terrashift_networks(model).state_dict()
    for name, tensor in expected.items():
        entry = f"networks[{name!r}]"
        stored = weights.get(name)
        if not isinstance(stored, torch.Tensor):
            raise _refused(
                path,
                entry,
                f"is missing: model_config's network has a {list(tensor.shape)} tensor there",
            )
        if stored.shape != tensor.shape:
            raise _refused(
                path,
                entry,
                f"has shape {list(stored.shape)} where model_config's network has "
                f"{list(tensor.shape)}: the weights and model_config disagree",
            )
    extra = [name for name in weights if name not in expected]
    if extra:
        raise _refused(
            path, f"networks[{shown(extra[0])}]", "is not a weight of model_config's network"
        )
    _check_finite(weights, path, "networks")


def _check_finite(value: Any, path: str | Path, entry: str) -> None:
    """Every floating-point tensor in ``value`` (nested in dicts and lists) is finite."""
    if isinstance(value, torch.Tensor):
        if value.is_floating_point() and not torch.isfinite(value).all():
            raise _refused(path, entry, "holds NaN or infinite values")
    elif isinstance(value, dict):
        for key, entry_value in value.items():
            _check_finite(entry_value, path, f"{entry}[{key!r}]")
    elif isinstance(value, list):
        for index, entry_value in enumerate(value):
            _check_finite(entry_value, path, f"{entry}[{index}]")


def _refused(path: str | Path, entry: str, what: str) -> ValueError:
    return ValueError(f"checkpoint {path}, entry {entry}: {what}")


def _memory_bytes() -> int:
    return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")


def _check_nesting(state: dict, path: Path) -> None:
    """Refuses lists and dicts nested deeper than :data:`MAX_DEPTH` or holding more than
    :data:`MAX_ENTRIES` entries, walking them without recursion."""
    stack, entries = [(state, 1)], 0
    while stack:
        value, depth = stack.pop()
        if depth > MAX_DEPTH:
            raise ValueError(
                f"checkpoint {path} nests lists or dicts more than {MAX_DEPTH} deep; a "
                "checkpoint never does"
            )
        children = value.values() if isinstance(value, dict) else value
        entries += len(children)
        if entries > MAX_ENTRIES:
            raise ValueError(
                f"checkpoint {path} holds more than {MAX_ENTRIES:,} entries in lists and dicts; "
                "a checkpoint never does"
            )
        stack.extend((child, depth + 1) for child in children if isinstance(child, dict | list))


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
    - ``run_seconds``: absent before a resumed run's clock went on from its checkpoint, 0.
    - ``schedule_start``: absent before the schedules could start again, 0; and
      ``curriculum_config.restart_schedules`` then false.
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
        state.setdefault("run_seconds", 0.0)
        state.setdefault("schedule_start", 0)
    if "curriculum_config" in state:
        state["curriculum_config"] = {"restart_schedules": False, **state["curriculum_config"]}
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
    trainer: OnPolicyTrainer,
    configs: dict,
    run_id: str | None,
    best: dict[str, Any],
    run_seconds: float,
) -> dict:
    """What ``last.pt`` holds: the trainer's state, the configs, the logger's run, the best
    reward's window and the seconds the run has spent in its training loop, over every part
    (a resumed run's clock goes on from them). In a data-parallel run every rank calls it (a
    collective)."""
    return {
        **trainer.state_dict(),
        **configs,
        "logger_run_id": run_id,
        "best": best,
        "run_seconds": run_seconds,
    }


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
    train, loss and curriculum settings; execution, scoring and initialisation ones aside),
    naming the overrides that would continue it. A checkpoint from before the curriculum was
    trained without one."""
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
            if saved.get(key) != value and key not in (*EXECUTION_SETTINGS, *SCORING_SETTINGS):
                differ.append(override(f"{group}.{key}", saved.get(key)))
    if differ:
        raise ValueError(
            f"run.resume={path} was trained with other settings; add {' '.join(differ)} to "
            "continue it (or start a new run from its weights with run.pretrained)"
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


def _rebuilt(value: Any, path: Path, entry: str) -> Any:
    if isinstance(value, list):
        return [_rebuilt(item, path, f"{entry}[{index}]") for index, item in enumerate(value)]
    if not isinstance(value, dict):
        return value
    if _TENSORDICT not in value:
        return {key: _rebuilt(item, path, f"{entry}[{key!r}]") for key, item in value.items()}
    stored = value[_TENSORDICT]
    if not (
        isinstance(stored, dict)
        and set(stored) == {"batch_size", "entries"}
        and isinstance(stored["entries"], dict)
        and isinstance(stored["batch_size"], list)
        and all(type(size) is int and 0 <= size < 2**31 for size in stored["batch_size"])
    ):
        raise _refused(
            path,
            f"{entry}[{_TENSORDICT!r}]",
            "must be a tensordict as save_checkpoint stores it: "
            "{'batch_size': [sizes], 'entries': {name: tensor or tensordict}}",
        )
    entries = {
        key: _rebuilt(item, path, f"{entry}[{key!r}]") for key, item in stored["entries"].items()
    }
    try:
        return TensorDict(entries, batch_size=stored["batch_size"])
    except (RuntimeError, ValueError, TypeError) as error:
        raise _refused(
            path, entry, f"is not a tensordict: {str(error).splitlines()[0][:200]}"
        ) from None
