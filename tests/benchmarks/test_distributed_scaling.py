"""distributed_scaling.py launches the recipe under torchrun and reads its logged throughput."""

import json
import subprocess
import sys
from pathlib import Path

import pytest

SCRIPT = Path(__file__).parents[2] / "benchmarks" / "distributed_scaling.py"


@pytest.mark.slow
def test_the_smoke_setting_runs_on_one_and_two_cpu_processes(tmp_path):
    out = tmp_path / "scaling.json"
    command = [sys.executable, str(SCRIPT), "--smoke", "--processes", "1", "2"]
    result = subprocess.run(
        [*command, "--warmup", "1", "--iters", "1", "--out", str(out)],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert result.returncode == 0, result.stderr
    rows = json.loads(out.read_text())["rows"]
    assert [row["processes"] for row in rows] == [1, 2]
    assert all(row["env_steps_per_s"] > 0 for row in rows)
    assert rows[0]["speedup"] == rows[0]["efficiency"] == 1.0
