"""Checkpoints written atomically and loaded without running code.

A run killed mid-write keeps the previous checkpoint. Loading uses ``torch.load`` with
``weights_only=True``: a checkpoint may hold tensors, numbers, strings, lists and dicts, nothing
that unpickling would have to construct by calling Python code, so a shared file cannot run
anything. Tensordicts (the trainer's carried state, also inside the lists and dicts of a
data-parallel run's per-rank states) are stored as nested dicts of tensors with their batch sizes
and rebuilt on loading.
"""

from __future__ import annotations

import os
import pickle
import re
import tempfile
import time
import zipfile
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import torch
from tensordict import TensorDict, TensorDictBase

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
    return {key: _rebuilt(value) for key, value in state.items()}


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
