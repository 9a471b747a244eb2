"""plot_training.py: learning curves against env-steps or minutes, one colour per run."""

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

BENCHMARKS = Path(__file__).parents[2] / "benchmarks"
sys.path.insert(0, str(BENCHMARKS))

from plot_training import panel_curve  # noqa: E402


def write_scalars(folder: Path, series: dict[str, list[tuple[int, float]]]) -> Path:
    folder.mkdir(parents=True)
    for metric, rows in series.items():
        (folder / f"{metric}.csv").write_text("".join(f"{s},{v}\n" for s, v in rows))
    return folder


@pytest.fixture
def runs(tmp_path: Path) -> tuple[Path, Path]:
    """A run with a clock (an iteration of 1,000 env-steps every 30 s) and a curriculum stage,
    and an older one with neither."""
    clocked = write_scalars(
        tmp_path / "clocked",
        {
            "run_seconds": [(1000 * i, 30.0 * i) for i in range(1, 11)],
            "eval_goal_fraction": [(2500, 0.1), (10000, 0.5)],
            "curriculum_stage": [(1000 * i, 1.0 + (i > 5)) for i in range(1, 11)],
        },
    )
    plain = write_scalars(tmp_path / "plain", {"eval_goal_fraction": [(4000, 0.2)]})
    return clocked, plain


def test_minutes_are_the_clock_at_each_points_env_steps(runs):
    clocked, plain = runs
    x, values = panel_curve(clocked, "eval_goal_fraction@minutes")
    np.testing.assert_allclose(x, [1.25, 5.0])  # 75 s and 300 s
    assert values == [0.1, 0.5]
    x, _ = panel_curve(clocked, "eval_goal_fraction")
    np.testing.assert_allclose(x, [0.0025, 0.01])
    assert panel_curve(plain, "eval_goal_fraction@minutes")[1] == []


def plot(*arguments: str) -> subprocess.CompletedProcess:
    command = [sys.executable, str(BENCHMARKS / "plot_training.py"), *arguments]
    return subprocess.run(command, capture_output=True, text=True, timeout=300)


def test_a_run_without_a_panels_series_is_left_out_of_that_panel(runs, tmp_path):
    out = tmp_path / "curves.png"
    metrics = ["eval_goal_fraction", "eval_goal_fraction@minutes", "curriculum_stage"]
    result = plot(*map(str, runs), "--metrics", *metrics, "--out", str(out))
    assert result.returncode == 0, result.stderr
    assert Image.open(out).mode == "P"


@pytest.mark.parametrize(
    ("metrics", "message"),
    [
        (["eval_goal_fraction@hours"], "only @minutes may follow a metric"),
        (["kl_approx"], "no run has kl_approx"),
    ],
)
def test_a_panel_no_run_can_draw_is_refused_by_name(runs, tmp_path, metrics, message):
    result = plot(*map(str, runs), "--metrics", *metrics, "--out", str(tmp_path / "x.png"))
    assert result.returncode != 0 and message in result.stderr
