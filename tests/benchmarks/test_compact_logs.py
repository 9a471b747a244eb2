"""compact_logs.py: a run summary reads like the CSV folder it was made from."""

import json
import math
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).parents[2] / "benchmarks"))

from common import read_evaluations, read_series, run_label  # noqa: E402
from compact_logs import summarize  # noqa: E402


@pytest.fixture
def scalars(tmp_path: Path) -> Path:
    """A CSVLogger folder of 100 iterations: three per-iteration metrics, one periodic one (every
    25th iteration), a NaN success rate, and an evaluation file beside it."""
    folder = tmp_path / "run_a"
    folder.mkdir()
    steps = [1000 * (i + 1) for i in range(100)]
    rows = {
        "reward_per_decision": [0.01 * i for i in range(100)],
        "success_rate": [math.nan if i == 3 else 0.5 for i in range(100)],
        "loss_total": [1.0] * 100,
    }
    for metric, values in rows.items():
        (folder / f"{metric}.csv").write_text(
            "".join(f"{s},{v}\n" for s, v in zip(steps, values, strict=True))
        )
    (folder / "eval_goal_fraction.csv").write_text("25000,0.1\n50000,0.2\n75000,0.3\n")
    scores = {"deterministic": {"goal_fraction": 0.25}}
    (tmp_path / "run_a_evaluation.json").write_text(json.dumps(scores))
    (tmp_path / "run_a_b_evaluation.json").write_text("{}")  # another run's ("run_a_b")
    return folder


def test_summary_keeps_the_tail_exact_and_bins_the_rest(scalars, tmp_path):
    summary = summarize(scalars, name="run_a", points=10, tail=16, device="cpu", date=None)
    assert summary["iterations"] == 100 and summary["device"] == "cpu" and "date" not in summary
    path = tmp_path / "run_a.json"
    path.write_text(json.dumps(summary))
    steps, reward = read_series(path, "reward_per_decision")
    full_steps, full_reward = read_series(scalars, "reward_per_decision")
    assert steps[-16:] == full_steps[-16:] and reward[-16:] == pytest.approx(full_reward[-16:])
    assert len(steps) == 10 + 16  # 84 iterations in bins of ceil(84 / 10) = 9: 9 bins and 1 of 3
    assert steps[0] == 9000 and reward[0] == pytest.approx(0.04)  # mean of 0.00 ... 0.08
    assert steps[9] == 84000 and reward[9] == pytest.approx(0.82)  # mean of 0.81 ... 0.83
    success = read_series(path, "success_rate")[1]
    assert success[0] == pytest.approx(0.5)  # the NaN is skipped in its bin
    assert read_series(path, "eval_goal_fraction") == ([25000, 50000, 75000], [0.1, 0.2, 0.3])
    assert read_series(path, "entropy") == ([], [])
    assert read_evaluations(path) == read_evaluations(scalars)
    assert read_evaluations(scalars) == {"evaluation": {"deterministic": {"goal_fraction": 0.25}}}
    assert run_label(path) == "run_a"


def test_the_curves_kept_are_those_drawn_or_named_and_every_evaluation(scalars):
    def kept(**metrics):
        summary = summarize(scalars, name="run_a", points=10, tail=16, **metrics)
        assert list(summary["sparse"]) == ["eval_goal_fraction"]
        return sorted(summary["series"])

    assert kept() == ["reward_per_decision", "success_rate"]  # loss_total is not drawn
    assert kept(metrics=None) == ["loss_total", "reward_per_decision", "success_rate"]
    assert kept(metrics=["loss_total"]) == ["loss_total"]


def test_a_folder_without_the_reward_is_refused(tmp_path):
    with pytest.raises(SystemExit, match="no reward_per_decision"):
        summarize(tmp_path, name="x", points=10, tail=16)


def test_a_recipes_folder_is_labelled_by_its_run_and_overrides_another_by_its_parent(tmp_path):
    own = tmp_path / "seed_7" / "logs" / "mapoca_pretrain" / "scalars"
    own.mkdir(parents=True)
    (tmp_path / "seed_7" / ".hydra").mkdir()
    (tmp_path / "seed_7" / ".hydra" / "overrides.yaml").write_text("- run.seed=7\n- env=large\n")
    assert run_label(own) == "seed_7 run.seed=7 env=large"
    copied = tmp_path / "copied" / "scalars"
    copied.mkdir(parents=True)
    assert run_label(copied) == "copied"
    assert run_label(Path("/scalars")) == "scalars"  # no run directory above it
