"""What the benchmark scripts share: the device's name, how results are written and read."""

from __future__ import annotations

import csv
import json
import os
import platform
from pathlib import Path

import torch
from omegaconf import OmegaConf


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


def write_results(path: Path, payload: dict) -> None:
    """Writes ``payload`` as JSON through a temporary file, so the file is never half-written
    (scripts call it after every measured row: a run stopped part-way keeps its rows)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    partial = path.with_name(path.name + ".partial")
    partial.write_text(json.dumps(payload, indent=2))
    partial.replace(path)


def read_series(folder: Path, metric: str) -> tuple[list[float], list[float]]:
    """Steps and values of one metric of a torchrl CSVLogger ``scalars`` folder (``<metric>.csv``
    of ``step,value`` rows); empty lists if the run did not log it."""
    path = folder / f"{metric}.csv"
    if not path.is_file():
        return [], []
    with path.open() as file:
        rows = [(float(step), float(value)) for step, value in csv.reader(file)]
    return [step for step, _ in rows], [value for _, value in rows]


def run_label(folder: Path) -> str:
    """A run's name in tables and legends. A recipe's own log folder,
    ``<run dir>/logs/<run name>/scalars``, is named by its run directory and the command line's
    overrides that Hydra recorded there (so the runs of a ``-m`` sweep tell apart); any other
    folder, such as a copy under ``benchmarks/results/training/``, by its own name."""
    if folder.name != "scalars":
        return folder.name
    run_dir = folder.resolve().parents[2]
    overrides = run_dir / ".hydra" / "overrides.yaml"
    if not overrides.is_file():
        return run_dir.name
    return " ".join([run_dir.name, *OmegaConf.load(overrides)])
