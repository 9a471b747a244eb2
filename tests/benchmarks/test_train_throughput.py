"""train_throughput.py --recipe: the recipe's own trainer, with its overrides, timed as a row."""

import json
import sys
from pathlib import Path

import pytest
import torch

sys.path.insert(0, str(Path(__file__).parents[2] / "benchmarks"))

import train_throughput  # noqa: E402


def test_the_recipe_row_has_the_overridden_batch_shape_and_its_split(monkeypatch, tmp_path):
    out = tmp_path / "recipe.json"
    overrides = [
        "model=small",
        "train.num_envs=8",
        "train.steps_per_iteration=4",
        "train.compile=false",
    ]
    argv = ["train_throughput.py", "--recipe", "--device", "cpu", "--warmup", "1", "--iters", "2"]
    monkeypatch.setattr(sys, "argv", [*argv, "--out", str(out), "--overrides", *overrides])
    cache = tmp_path / "inductor"
    (cache / "fxgraph").mkdir(parents=True)
    (cache / "fxgraph" / "entry").write_bytes(b"graph")
    monkeypatch.setenv("TORCHINDUCTOR_CACHE_DIR", str(cache))
    torch.set_num_threads(1)
    train_throughput.main()
    payload = json.loads(out.read_text())
    assert payload["overrides"] == overrides
    assert payload["inductor_cache"] == {"folder": str(cache), "files": 1}
    (row,) = payload["rows"]
    assert (row["num_envs"], row["steps_per_iteration"], row["epochs"]) == (8, 4, 2)
    # on the CPU neither TF32 nor CUDA graphs apply, whatever the recipe sets
    assert (row["precision"], row["execution"]) == ("fp32", "eager")
    assert min(row[f"{part}_seconds"] for part in ("collection", "estimation", "epochs")) > 0
    assert row["env_steps_per_s"] * row["iteration_seconds"] == pytest.approx(8 * 4, rel=1e-4)
