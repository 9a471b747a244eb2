"""results_table.py: a run's periodic evaluations, of its mean action and of its samples."""

import json
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).parents[2] / "benchmarks"))

from results_table import METRICS, row, scores  # noqa: E402


def write_run(folder: Path, *, sampled: bool) -> Path:
    """A CSVLogger folder: reward every iteration, evaluations at 100 and 200 env-steps (the
    samples' scores a tenth above the mean action's)."""
    folder.mkdir()
    (folder / "reward_per_decision.csv").write_text("50,0.1\n100,0.2\n150,0.3\n200,0.4\n")
    prefixes = {"eval_": 1.0, "eval_sampled_": 1.1} if sampled else {"eval_": 1.0}
    for prefix, factor in prefixes.items():
        for index, (name, _) in enumerate(METRICS):
            values = [(index + 1) * step / 1000 * factor for step in (100, 200)]
            (folder / f"{prefix}{name}.csv").write_text(f"100,{values[0]}\n200,{values[1]}\n")
    return folder


def test_sampled_periodic_evaluations_are_read_beside_the_mean_actions(tmp_path):
    run = write_run(tmp_path / "both", sampled=True)
    last = scores(run)
    assert last["deterministic"]["goal_fraction"] == pytest.approx(0.2)
    assert last["stochastic"]["goal_fraction"] == pytest.approx(0.22)
    at = scores(run, at=100)
    assert at["stochastic"]["success_rate"] == pytest.approx(0.22)
    cells = row("recipe", [run, run], at=100)
    assert cells[3] == "0.100 ± 0.000 (0.110 ± 0.000)"
    with pytest.raises(SystemExit, match="no evaluation at 150"):
        scores(run, at=150)


def test_a_run_without_sampled_evaluations_shows_its_mean_actions_alone(tmp_path):
    run = write_run(tmp_path / "mean", sampled=False)
    assert list(scores(run)) == ["deterministic"]
    assert row("recipe", [run], at=200)[3] == "0.200"


def test_a_finetunes_zero_shot_row_has_no_training_reward_yet(tmp_path):
    run = write_run(tmp_path / "finetune", sampled=False)
    for name, _ in METRICS:  # the pretrained weights' score, logged before any iteration
        logged = run / f"eval_{name}.csv"
        logged.write_text("0,0.05\n" + logged.read_text())
    cells = row("recipe", [run, run], at=0)
    assert cells[3] == "0.050 ± 0.000" and cells[-1] == ""
    assert row("recipe", [run], at=100)[-1] == "+0.150"  # the mean of 0.1 and 0.2


def test_a_run_in_parts_is_scored_at_any_budget_of_its_parts(tmp_path):
    first = write_run(tmp_path / "part0", sampled=False)
    second = tmp_path / "part1"  # the resumed part: evaluation at 300, rewards from 250
    second.mkdir()
    (second / "reward_per_decision.csv").write_text("250,0.5\n300,0.6\n")
    for index, (name, _) in enumerate(METRICS):
        (second / f"eval_{name}.csv").write_text(f"300,{(index + 1) * 0.3}\n")
    joined = f"{first}+{second}"
    assert scores(joined, at=100)["deterministic"]["goal_fraction"] == pytest.approx(0.1)
    assert scores(joined)["deterministic"]["goal_fraction"] == pytest.approx(0.3)
    cells = row("recipe", [joined], at=300)
    assert cells[2] == "0.0 M" and cells[3] == "0.300"
    assert cells[-1] == "+0.350"  # the mean of the six rewards logged up to 300


def test_the_evaluation_file_read_is_chosen_by_its_suffix(tmp_path):
    run = write_run(tmp_path / "curriculum", sampled=False)
    for suffix, goals in (("evaluation", 0.9), ("pretraining_scene_evaluation", 0.7)):
        scored = {name: goals for name, _ in METRICS}
        report = {"deterministic": scored, "stochastic": scored}
        (tmp_path / f"curriculum_{suffix}.json").write_text(json.dumps(report))
    assert row("recipe", [run])[3] == "0.900 (0.900)"
    assert row("recipe", [run], file="pretraining_scene_evaluation")[3] == "0.700 (0.700)"
    assert row("recipe", [run], at=200)[3] == "0.200"  # a budget reads the periodic ones
