"""vmas_parity.py: final reward and AUC of each curve, their spread over seeds, and the table."""

import json
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).parents[2] / "benchmarks"))

from vmas_parity import (  # noqa: E402
    TRAINING_ARGS,
    main,
    markdown,
    merge,
    read_output,
    scores,
    summarise,
)


def test_final_is_the_mean_of_the_last_points_and_auc_the_mean_of_all():
    curve = [0.0, 1.0, 2.0, 3.0, 4.0]
    assert scores(curve, 2) == {"final": 3.5, "auc": 2.0}


def test_summary_gives_mean_and_sd_over_seeds_and_the_ratio_of_the_means():
    curves = {
        "MAPOCA": {0: [0.0, 2.0], 1: [2.0, 4.0]},
        "MAPPO": {0: [1.0, 1.0], 1: [1.0, 3.0]},
    }
    table = summarise(curves, final_iterations=1)
    assert table["MAPOCA"]["final"]["per_seed"] == [2.0, 4.0]
    assert table["MAPOCA"]["final"]["mean"] == 3.0
    assert table["MAPOCA"]["final"]["sd"] == pytest.approx(2**0.5)
    assert table["MAPOCA"]["auc"]["mean"] == 2.0
    assert table["MAPPO"]["auc"]["mean"] == 1.5
    assert table["MAPOCA_vs_MAPPO"]["final"]["ratio"] == pytest.approx(1.5)
    assert table["MAPOCA_vs_MAPPO"]["auc"]["difference"] == pytest.approx(0.5)


def test_table_is_redrawn_from_an_output_file(tmp_path, capsys):
    curves = {"MAPOCA": {0: [0.5, 1.0], 1: [0.5, 1.0]}, "MAPPO": {0: [0.5, 0.5], 1: [0.5, 0.5]}}
    result = {"args": {"env": "vmas:balance"}, "table": summarise(curves, final_iterations=1)}
    path = tmp_path / "vmas_parity_balance.json"
    path.write_text(json.dumps(result))
    main(["--table", str(path)])
    printed = capsys.readouterr().out.strip()
    assert printed == markdown([json.loads(path.read_text())])
    rows = printed.splitlines()[2:]
    assert rows[0].split("|")[1:4] == [" balance ", " MAPOCA ", " 2 "]
    assert "+1.0000 ± 0.0000" in rows[0] and "| 2.000 | 1.500 |" in rows[0]
    assert rows[1].split("|")[2] == " MAPPO " and rows[1].endswith("|  |  |")


def _output(method: str, curves: dict, **settings) -> dict:
    args = {key: 1 for key in TRAINING_ARGS} | {"env": "vmas:balance"} | settings
    return {"args": args, "date": "2026-11-25", "curves": {method: curves}}


def test_merge_puts_the_methods_of_runs_with_the_same_settings_together():
    mapoca = _output("MAPOCA", {"0": [0.0, 1.0], "1": [1.0, 3.0]})
    mappo = _output("MAPPO", {"0": [0.5, 0.5], "1": [0.5, 1.5]})
    del mappo["args"]["critic_depth"]  # an output of the example before it had the option
    mapoca["args"]["critic_depth"] = 2
    merged = merge([mapoca, mappo], final_iterations=1)
    assert merged["curves"]["MAPOCA"] == {0: [0.0, 1.0], 1: [1.0, 3.0]}
    assert merged["table"]["MAPOCA_vs_MAPPO"]["final"]["ratio"] == 2.0
    assert [source["runs"] for source in merged["sources"]] == [
        {"MAPOCA": ["0", "1"]},
        {"MAPPO": ["0", "1"]},
    ]


def test_merge_refuses_runs_of_other_settings_or_the_same_run_twice():
    mapoca = _output("MAPOCA", {"0": [0.0, 1.0]})
    with pytest.raises(ValueError, match="differ in lr"):
        merge([mapoca, _output("MAPPO", {"0": [0.5, 0.5]}, lr=2)], final_iterations=1)
    with pytest.raises(ValueError, match="MAPOCA seed 0 is in more than one output"):
        merge([mapoca, mapoca], final_iterations=1)


def test_table_names_the_warm_up_of_ma_pocas_advantages():
    curves = {"MAPOCA": {0: [0.5, 1.0]}, "MAPPO": {0: [0.5, 0.5]}}
    table = summarise(curves, final_iterations=1)
    result = {"args": {"env": "vmas:navigation", "counterfactual_warmup": 20}, "table": table}
    rows = markdown([result]).splitlines()[2:]
    assert [row.split("|")[2] for row in rows] == [" MAPOCA, warm-up 20 ", " MAPPO "]


def test_merge_takes_mappo_runs_beside_mapoca_runs_of_another_warm_up():
    mapoca = _output("MAPOCA", {"0": [0.0, 1.0]}, counterfactual_warmup=20)
    mappo = _output("MAPPO", {"0": [0.5, 0.5]}, counterfactual_warmup=0)
    merged = merge([mapoca, mappo], final_iterations=1)
    assert merged["args"]["counterfactual_warmup"] == 20
    assert merged["table"]["MAPOCA_vs_MAPPO"]["final"]["ratio"] == 2.0
    other = _output("MAPOCA", {"1": [0.0, 1.0]}, counterfactual_warmup=0)
    with pytest.raises(ValueError, match="differ in counterfactual_warmup"):
        merge([mapoca, other, mappo], final_iterations=1)


def test_merge_reads_one_method_of_a_file(tmp_path):
    both = _output("MAPOCA", {"0": [0.0, 1.0]}, counterfactual_warmup=0)
    both["curves"]["MAPPO"] = {"0": [0.5, 0.5]}
    path = tmp_path / "both.json"
    path.write_text(json.dumps(both))
    assert read_output(f"{path}:MAPPO")["curves"] == {"MAPPO": {"0": [0.5, 0.5]}}
    assert read_output(str(path))["curves"] == both["curves"]
    warm = _output("MAPOCA", {"0": [0.0, 2.0]}, counterfactual_warmup=20)
    merged = merge([warm, read_output(f"{path}:MAPPO")], final_iterations=1)
    assert merged["table"]["MAPOCA_vs_MAPPO"]["final"]["ratio"] == 4.0
    (tmp_path / "warm.json").write_text(json.dumps(warm))
    with pytest.raises(ValueError, match="warm.json holds no MAPPO runs"):
        read_output(f"{tmp_path / 'warm.json'}:MAPPO")


def test_table_gives_the_same_mappo_runs_of_two_outputs_once():
    mappo = {0: [0.5, 0.5]}
    outputs = [
        {
            "args": {"env": "vmas:balance", "counterfactual_warmup": warmup},
            "table": summarise({"MAPOCA": {0: [0.5, value]}, "MAPPO": mappo}, final_iterations=1),
        }
        for warmup, value in ((0, 0.25), (20, 1.0))
    ]
    rows = markdown(outputs).splitlines()[2:]
    assert [row.split("|")[2] for row in rows] == [" MAPOCA ", " MAPPO ", " MAPOCA, warm-up 20 "]
