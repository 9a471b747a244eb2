"""What the benchmark scripts share: their command line's basics, the header of a results file,
how a table is printed, and how results are written and read."""

from __future__ import annotations

import argparse
import ast
import csv
import dataclasses
import json
import math
import os
import platform
import shlex
import sys
from collections.abc import Callable, Iterable
from datetime import date
from pathlib import Path

import numpy as np
import torch
from omegaconf import OmegaConf


def field_parser(config: type) -> Callable[[str], tuple[str, object]]:
    """An argparse type: ``FIELD=VALUE`` with FIELD a field of the dataclass ``config`` and VALUE
    a Python literal (``embed_dim=64``, ``cnn_channels=[8,16,16]``), parsed to ``(FIELD, value)``;
    anything else refused naming the fields."""
    fields = {field.name for field in dataclasses.fields(config)}

    def parse(text: str) -> tuple[str, object]:
        field, sep, value = text.partition("=")
        if not sep or field not in fields:
            raise argparse.ArgumentTypeError(
                f"{text!r} is not FIELD=VALUE with FIELD one of {config.__name__}'s: "
                + ", ".join(sorted(fields))
            )
        try:
            return field, ast.literal_eval(value)
        except (ValueError, SyntaxError):
            raise argparse.ArgumentTypeError(
                f"{text!r}: {value!r} is not a Python literal"
            ) from None

    return parse


def benchmark_parser(doc: str, *, device: bool = False) -> argparse.ArgumentParser:
    """The parser a script starts from: its docstring's first line as the description and the
    rest, the usage examples, after the options in ``--help``; with ``device``, a ``--device``
    option (CUDA when present, else the CPU)."""
    summary, _, usage = doc.partition("\n")
    parser = argparse.ArgumentParser(
        description=summary, epilog=usage, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    if device:
        parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    return parser


def run_header(device: torch.device) -> dict:
    """What heads every results file: the date, the device's name, torch's version and the
    command that wrote it."""
    return {
        "date": date.today().isoformat(),
        "device": device_name(device),
        "torch": torch.__version__,
        "command": shlex.join(["python", *sys.argv]),
    }


def inductor_cache() -> dict:
    """Inductor's cache folder (``TORCHINDUCTOR_CACHE_DIR``, else torch's default) and the files
    it holds: a compiled update found there takes seconds to load instead of about a minute to
    compile, which a run's time to goal shows."""
    from torch._inductor.runtime.cache_dir_utils import default_cache_dir

    folder = Path(os.environ.get("TORCHINDUCTOR_CACHE_DIR") or default_cache_dir()).resolve()
    files = sum(path.is_file() for path in folder.rglob("*")) if folder.is_dir() else 0
    return {"folder": str(folder), "files": files}


def table_row(cells: Iterable[object]) -> str:
    """One row of a Markdown table, the form in which every script prints its results."""
    return "| " + " | ".join(str(cell) for cell in cells) + " |"


def table_header(names: Iterable[str]) -> str:
    """A Markdown table's header row and the rule under it."""
    names = list(names)
    return table_row(names) + "\n" + table_row("---" for _ in names)


def device_name(device: torch.device) -> str:
    """The GPU's name, or the processor's model name and core count (Linux)."""
    if device.type == "cuda":
        return torch.cuda.get_device_name(device)
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return f"{line.split(':', 1)[1].strip()} ({os.cpu_count()} cores)"
    except OSError:
        pass
    return platform.processor() or platform.machine()


def significant(value, digits: int = 6):
    """``value`` with every fractional float in it kept to ``digits`` significant digits (no
    measurement here resolves finer); whole numbers, other types and non-finite floats as
    they are."""
    if isinstance(value, float) and math.isfinite(value) and not value.is_integer():
        return float(f"{value:.{digits}g}")
    if isinstance(value, dict):
        return {key: significant(item, digits) for key, item in value.items()}
    if isinstance(value, list | tuple):
        return [significant(item, digits) for item in value]
    return value


def write_results(path: Path, payload: dict) -> None:
    """Writes ``payload`` as compact JSON, floats to six significant digits, through a
    temporary file, so the file is never half-written (scripts call it after every measured
    row: a run stopped part-way keeps its rows) and the results kept in git stay small."""
    path.parent.mkdir(parents=True, exist_ok=True)
    partial = path.with_name(path.name + ".partial")
    partial.write_text(json.dumps(significant(payload), separators=(",", ":")))
    partial.replace(path)


def save_palette_png(figure, out: Path, colors: int = 256) -> None:
    """Writes a drawn matplotlib ``figure`` to ``out`` as a PNG of at most ``colors`` colours
    (a third of a full-colour file's bytes for line plots)."""
    from PIL import Image  # matplotlib's own dependency

    figure.canvas.draw()
    pixels = np.asarray(figure.canvas.buffer_rgba())[..., :3]
    out.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(pixels).quantize(colors).save(out, optimize=True)
    print(f"wrote {out} ({out.stat().st_size / 1e3:.0f} kB)")


def read_series(run: Path, metric: str) -> tuple[list[float], list[float]]:
    """Steps and values of one metric of a run: a torchrl CSVLogger ``scalars`` folder
    (``<metric>.csv`` of ``step,value`` rows), a run summary written by ``compact_logs.py``
    or one seed of a ``time_to_goal.py`` result (:func:`read_summary`); empty lists if the run
    did not log it."""
    if is_summary(run):
        summary = read_summary(run)
        if metric in summary["series"]:
            return list(summary["steps"]), list(summary["series"][metric])
        points = summary["sparse"].get(metric, [])
        return [step for step, _ in points], [value for _, value in points]
    path = run / f"{metric}.csv"
    if not path.is_file():
        return [], []
    with path.open() as file:
        rows = [(float(step), float(value)) for step, value in csv.reader(file)]
    return [step for step, _ in rows], [value for _, value in rows]


def joined_series(run: str | Path, metric: str) -> tuple[list[float], list[float]]:
    """``metric``'s steps and values over a run's parts in order: runs continued with
    ``run.resume`` are named by their parts joined with ``+`` (``a.json+a_part1.json``)."""
    series = [read_series(part, metric) for part in run_parts(run)]
    return [s for steps, _ in series for s in steps], [v for _, values in series for v in values]


def run_parts(run: str | Path) -> list[Path]:
    """The parts of a run named ``a+b+...`` (one part for a plain path), each an existing
    summary or scalars folder: a mistyped name is refused, not drawn as a run without data."""
    parts = [Path(part) for part in str(run).split("+")]
    for part in parts:
        if not _seed_of(part)[0].exists():
            raise FileNotFoundError(f"run {run}: {part} is neither a summary nor a scalars folder")
    return parts


def is_summary(run: Path) -> bool:
    """Whether a run is a JSON summary (:func:`read_summary`) rather than a ``scalars`` folder."""
    return _seed_of(run)[0].suffix == ".json"


def _seed_of(run: Path) -> tuple[Path, str]:
    """A run's file and the seed that ``<result>.json#<seed>`` names ("" if none)."""
    name, _, seed = run.name.partition("#")
    return run.with_name(name), seed


def read_summary(path: Path) -> dict:
    """A run summary written by ``compact_logs.py``, or one drawn from one seed of a
    ``time_to_goal.py`` result (``<result>.json#<seed>``, or the file alone if it holds one
    seed): its evaluations' goal fractions as ``eval_goal_fraction``, their training seconds
    (evaluations not counted) as ``run_seconds`` and, for a curriculum run, its stages as
    ``curriculum_stage`` (steps at its ``stage_starts``), named by the file (and the seed).

    Raises:
        ValueError: for a ``time_to_goal.py`` result of several seeds without one named, a seed
            it does not hold, or a seed named after a file that is not such a result.
    """
    if path not in _SUMMARIES:
        file, seed = _seed_of(path)
        summary = json.loads(file.read_text())
        if "seeds" in summary:
            summary = _time_to_goal_summary(file, summary, seed)
        elif seed:
            raise ValueError(f"{path}: {file.name} is a run summary, not a time_to_goal result")
        _SUMMARIES[path] = summary
    return _SUMMARIES[path]


def _time_to_goal_summary(path: Path, result: dict, seed: str) -> dict:
    entries = {str(entry["seed"]): entry for entry in result["seeds"]}
    if not seed and len(entries) != 1:
        raise ValueError(
            f"{path}: a time_to_goal result of {len(entries)} seeds; a run to draw is one "
            f"seed's, {path}#<seed> (seeds {', '.join(entries)})"
        )
    if seed and seed not in entries:
        raise ValueError(f"{path}#{seed}: no seed {seed} in it (seeds {', '.join(entries)})")
    name = f"{path.stem}#{seed}" if seed else path.stem
    entry = entries[seed] if seed else result["seeds"][0]
    curve = entry["curve"]
    sparse = {
        "eval_goal_fraction": [[steps, goal] for steps, _, goal in curve],
        "run_seconds": [[steps, seconds] for steps, seconds, _ in curve],
    }
    if "stage_starts" in entry:
        stages = [[curve[0][0], 1]]
        for stage, start in enumerate(entry["stage_starts"], start=2):
            stages += [[start, stage - 1], [start, stage]]
        sparse["curriculum_stage"] = [*stages, [curve[-1][0], stages[-1][1]]]
    return {"run": name, "steps": [], "series": {}, "sparse": sparse, "evaluations": {}}


_SUMMARIES: dict[Path, dict] = {}


def read_evaluations(run: Path) -> dict[str, dict]:
    """A run's evaluation files (``recipes/evaluate.py``'s output), keyed by their suffix
    (:data:`EVALUATION_SUFFIXES`): for a ``scalars`` folder the files ``<folder>_<suffix>.json``
    beside it, for a summary the evaluations it holds."""
    if is_summary(run):
        return read_summary(run)["evaluations"]
    files = {suffix: run.with_name(f"{run.name}_{suffix}.json") for suffix in EVALUATION_SUFFIXES}
    return {
        suffix: json.loads(path.read_text()) for suffix, path in files.items() if path.is_file()
    }


EVALUATION_SUFFIXES = (
    "evaluation",
    "training_mode_evaluation",
    "best_evaluation",
    "best_training_mode_evaluation",
    "snapshots_evaluation",
    "pretraining_scene_evaluation",  # a larger scene's policy back on the pretraining scene
    "finetune_scene_evaluation",  # a larger scene's policy on the 30 x 30 finetune scene
)
"""How the evaluation files of a run's log folder are named: ``<folder>_<suffix>.json``."""


def run_label(run: Path) -> str:
    """A run's name in tables and legends. A summary carries its own; a recipe's own log
    folder, ``<run dir>/logs/<run name>/scalars``, is named by its run directory and the
    command line's overrides that Hydra recorded there (so the runs of a ``-m`` sweep tell
    apart); another ``scalars`` folder by its parent's name, any other folder by its own."""
    if is_summary(run):
        return read_summary(run)["run"]
    if run.name != "scalars":
        return run.name
    folder = run.resolve()
    if folder.parent.parent.name != "logs":
        return folder.parent.name or run.name
    run_dir = folder.parents[2]
    overrides = run_dir / ".hydra" / "overrides.yaml"
    if not overrides.is_file():
        return run_dir.name
    return " ".join([run_dir.name, *OmegaConf.load(overrides)])
