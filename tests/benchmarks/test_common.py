"""common.py: a run continued in parts is read as one series."""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parents[2] / "benchmarks"))

from common import joined_series  # noqa: E402


def test_a_runs_parts_joined_by_plus_make_one_series_in_order(tmp_path):
    for name, rows in (("part0", "64,0.1\n128,0.2\n"), ("part1", "192,0.3\n")):
        (tmp_path / name).mkdir()
        (tmp_path / name / "reward_per_decision.csv").write_text(rows)
    first, second = tmp_path / "part0", tmp_path / "part1"
    steps, values = joined_series(f"{first}+{second}", "reward_per_decision")
    assert steps == [64, 128, 192] and values == [0.1, 0.2, 0.3]
    assert joined_series(str(second), "reward_per_decision") == ([192], [0.3])
