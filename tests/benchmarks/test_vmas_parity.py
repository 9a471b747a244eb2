"""vmas_parity.py: final reward and AUC of each curve, their spread over seeds, and the table."""

import argparse
import json
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).parents[2] / "benchmarks"))

from vmas_parity import (  # noqa: E402
    REWARD_SHARING,
    TRAINING_ARGS,
    main,
    markdown,
    merge,
    read_output,
    scenario,
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
    table = summarise(curves, final_fraction=0.5)
    assert table["MAPOCA"]["final"]["per_seed"] == [2.0, 4.0]
    assert table["MAPOCA"]["final"]["mean"] == 3.0
    assert table["MAPOCA"]["final"]["sd"] == pytest.approx(2**0.5)
    assert table["MAPOCA"]["auc"]["mean"] == 2.0
    assert table["MAPPO"]["auc"]["mean"] == 1.5
    assert table["MAPOCA_vs_MAPPO"]["final"]["ratio"] == pytest.approx(1.5)
    assert table["MAPOCA_vs_MAPPO"]["auc"]["difference"] == pytest.approx(0.5)
    # MAPOCA's final reward is 1 above MAPPO's, the larger sd of the two sqrt(2)
    assert table["MAPOCA_vs_MAPPO"]["final"]["in_spreads"] == pytest.approx(2**-0.5)


def test_curves_are_scored_over_the_iterations_every_run_reached():
    curves = {"MAPOCA": {0: [0.0] * 10}, "MAPPO": {0: [1.0] * 20 + [5.0] * 20}}
    table = summarise(curves, final_fraction=0.1)
    assert (table["iterations"], table["final_iterations"]) == (10, 1)
    assert table["MAPPO"]["final"]["mean"] == table["MAPPO"]["auc"]["mean"] == 1.0
    assert summarise({"MAPPO": {0: list(range(40))}}, 0.1)["MAPPO"]["final"]["mean"] == 37.5


def test_scenarios_are_named_with_their_team_size_and_reward_sharing():
    assert scenario("balance:8") == ("balance", 8)
    assert scenario("navigation") == ("navigation", None)
    assert all(description for description in REWARD_SHARING.values())
    for bad, message in (("football:8", "unknown scenario 'football'"), ("wheel:1", "above 1")):
        with pytest.raises(argparse.ArgumentTypeError, match=message):
            scenario(bad)


def test_table_is_redrawn_from_an_output_file(tmp_path, capsys):
    curves = {"MAPOCA": {0: [0.5, 1.0], 1: [0.5, 1.5]}, "MAPPO": {0: [0.5, 0.5], 1: [0.5, 0.5]}}
    result = {"args": {"env": "vmas:balance", "agents": 8}, "curves": curves}
    path = tmp_path / "vmas_parity_balance_8agents.json"
    path.write_text(json.dumps(result))
    main(["--table", str(path), "--final-fraction", "0.5"])
    printed = capsys.readouterr().out.strip()
    assert printed == markdown([json.loads(path.read_text())], final_fraction=0.5)
    rows = printed.splitlines()[2:]
    assert rows[0].split("|")[1:5] == [" balance, 8 agents ", " MAPOCA ", " 2 ", " 2 "]
    # final: MAPOCA 1.25 ± 0.354 against MAPPO 0.5 ± 0: 0.75 above it, 2.1 of the larger sd
    assert "+1.2500 ± 0.3536" in rows[0] and "| +0.7500 (+2.1 sd) | +0.3750 (+2.1 sd) |" in rows[0]
    assert rows[1].split("|")[2] == " MAPPO " and rows[1].endswith("|  |  |")


def _output(method: str, curves: dict, **settings) -> dict:
    args = {key: 1 for key in TRAINING_ARGS} | {"env": "vmas:balance"} | settings
    return {"args": args, "date": "2026-11-25", "curves": {method: curves}}


def test_merge_puts_the_methods_of_runs_with_the_same_settings_together():
    mapoca = _output("MAPOCA", {"0": [0.0, 1.0], "1": [1.0, 3.0]})
    mappo = _output("MAPPO", {"0": [0.5, 0.5], "1": [0.5, 1.5]})
    del mappo["args"]["critic_depth"]  # an output of the example before it had the option
    mapoca["args"]["critic_depth"] = 2
    merged = merge([mapoca, mappo], final_fraction=0.5)
    assert merged["curves"]["MAPOCA"] == {0: [0.0, 1.0], 1: [1.0, 3.0]}
    assert merged["table"]["MAPOCA_vs_MAPPO"]["final"]["ratio"] == 2.0
    assert [source["runs"] for source in merged["sources"]] == [
        {"MAPOCA": ["0", "1"]},
        {"MAPPO": ["0", "1"]},
    ]


def test_merge_refuses_runs_of_other_settings_or_the_same_run_twice():
    mapoca = _output("MAPOCA", {"0": [0.0, 1.0]})
    with pytest.raises(ValueError, match="differ in lr"):
        merge([mapoca, _output("MAPPO", {"0": [0.5, 0.5]}, lr=2)], final_fraction=0.5)
    with pytest.raises(ValueError, match="MAPOCA seed 0 is in more than one output"):
        merge([mapoca, mapoca], final_fraction=0.5)


def test_table_names_the_warm_up_of_ma_pocas_advantages():
    curves = {"MAPOCA": {0: [0.5, 1.0]}, "MAPPO": {0: [0.5, 0.5]}}
    result = {"args": {"env": "vmas:navigation", "counterfactual_warmup": 20}, "curves": curves}
    rows = markdown([result], final_fraction=0.5).splitlines()[2:]
    assert [row.split("|")[2] for row in rows] == [" MAPOCA, warm-up 20 ", " MAPPO "]


def test_merge_takes_mappo_runs_beside_mapoca_runs_of_another_warm_up():
    mapoca = _output("MAPOCA", {"0": [0.0, 1.0]}, counterfactual_warmup=20)
    mappo = _output("MAPPO", {"0": [0.5, 0.5]}, counterfactual_warmup=0)
    merged = merge([mapoca, mappo], final_fraction=0.5)
    assert merged["args"]["counterfactual_warmup"] == 20
    assert merged["table"]["MAPOCA_vs_MAPPO"]["final"]["ratio"] == 2.0
    other = _output("MAPOCA", {"1": [0.0, 1.0]}, counterfactual_warmup=0)
    with pytest.raises(ValueError, match="differ in counterfactual_warmup"):
        merge([mapoca, other, mappo], final_fraction=0.5)


def test_merge_reads_one_method_of_a_file(tmp_path):
    both = _output("MAPOCA", {"0": [0.0, 1.0]}, counterfactual_warmup=0)
    both["curves"]["MAPPO"] = {"0": [0.5, 0.5]}
    path = tmp_path / "both.json"
    path.write_text(json.dumps(both))
    assert read_output(f"{path}:MAPPO")["curves"] == {"MAPPO": {"0": [0.5, 0.5]}}
    assert read_output(str(path))["curves"] == both["curves"]
    warm = _output("MAPOCA", {"0": [0.0, 2.0]}, counterfactual_warmup=20)
    merged = merge([warm, read_output(f"{path}:MAPPO")], final_fraction=0.5)
    assert merged["table"]["MAPOCA_vs_MAPPO"]["final"]["ratio"] == 4.0
    (tmp_path / "warm.json").write_text(json.dumps(warm))
    with pytest.raises(ValueError, match="warm.json holds no MAPPO runs"):
        read_output(f"{tmp_path / 'warm.json'}:MAPPO")


def test_table_gives_the_same_mappo_runs_of_two_outputs_once():
    mappo = {0: [0.5, 0.5]}
    outputs = [
        {
            "args": {"env": "vmas:balance", "counterfactual_warmup": warmup},
            "curves": {"MAPOCA": {0: [0.5, value]}, "MAPPO": mappo},
        }
        for warmup, value in ((0, 0.25), (20, 1.0))
    ]
    rows = markdown(outputs, final_fraction=0.5).splitlines()[2:]
    assert [row.split("|")[2] for row in rows] == [" MAPOCA ", " MAPPO ", " MAPOCA, warm-up 20 "]


def test_a_grid_runs_both_methods_on_every_scenario_and_stops_at_the_deadline(tmp_path, capsys):
    """Two VMAS scenarios, both losses, one seed, on the CPU; with a deadline already past,
    every run stops after its first iteration of the three asked for. One worker process runs
    them one after the other (it imports torch once)."""
    pytest.importorskip("vmas")
    tiny = ["--iterations", "3", "--num-envs", "2", "--episode-steps", "4", "--epochs", "1"]
    tiny += ["--minibatch-size", "8", "--width", "8"]
    main(
        ["--scenarios", "balance:2", "wheel:2", "--seeds", "0", "--deadline", "0", "--jobs", "1"]
        + ["--out-dir", str(tmp_path), *tiny]
    )
    summary = json.loads((tmp_path / "summary.json").read_text())
    names = ["vmas_parity_balance_2agents.json", "vmas_parity_wheel_2agents.json"]
    assert sorted(summary["scenarios"]) == names and summary["failed"] == []
    for name in names:
        result = json.loads((tmp_path / name).read_text())
        assert result["reward_sharing"] == REWARD_SHARING[name.split("_")[2]]
        assert result["args"]["agents"] == 2 and result["args"]["counterfactual_warmup"] == 20
        assert result["table"]["iterations"] == 1
        assert {m: sorted(runs) for m, runs in result["curves"].items()} == {
            "MAPOCA": ["0"],
            "MAPPO": ["0"],
        }
        assert all(len(curve) == 1 for runs in result["curves"].values() for curve in runs.values())
        assert summary["scenarios"][name]["table"] == result["table"]
    rows = capsys.readouterr().out.strip().splitlines()[-4:]
    labels = ["balance, 2 agents", "balance, 2 agents", "wheel, 2 agents", "wheel, 2 agents"]
    assert [row.split("|")[1].strip() for row in rows] == labels
