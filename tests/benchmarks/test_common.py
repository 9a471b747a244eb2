"""common.py: a run continued in parts is read as one series; the shared command line, header
and table."""

import argparse
import json
import math
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parents[2] / "benchmarks"))

import pytest  # noqa: E402
import torch  # noqa: E402
from common import (  # noqa: E402
    benchmark_parser,
    field_parser,
    inductor_cache,
    joined_series,
    run_header,
    table_header,
    table_row,
    write_results,
)


def test_a_runs_parts_joined_by_plus_make_one_series_in_order(tmp_path):
    for name, rows in (("part0", "64,0.1\n128,0.2\n"), ("part1", "192,0.3\n")):
        (tmp_path / name).mkdir()
        (tmp_path / name / "reward_per_decision.csv").write_text(rows)
    first, second = tmp_path / "part0", tmp_path / "part1"
    steps, values = joined_series(f"{first}+{second}", "reward_per_decision")
    assert steps == [64, 128, 192] and values == [0.1, 0.2, 0.3]
    assert joined_series(str(second), "reward_per_decision") == ([192], [0.3])
    with pytest.raises(FileNotFoundError, match="part2 is neither a summary nor a scalars"):
        joined_series(f"{first}+{tmp_path / 'part2'}", "reward_per_decision")


def test_results_keep_six_significant_digits_and_whole_numbers_exactly(tmp_path):
    out = tmp_path / "results.json"
    rows = [[0.123456789, 2], (1e-9 / 3,)]
    payload = {"rate": 91234.5678, "steps": 33554432.0, "rows": rows, "inf": math.inf, "name": "a"}
    write_results(out, payload)
    assert json.loads(out.read_text()) == {
        "rate": 91234.6,
        "steps": 33554432.0,
        "rows": [[0.123457, 2], [3.33333e-10]],
        "inf": math.inf,
        "name": "a",
    }
    assert not list(tmp_path.glob("*.partial"))


def test_a_benchmark_prints_a_markdown_table():
    assert table_header(["envs", "env-steps/s"]) == "| envs | env-steps/s |\n| --- | --- |"
    assert table_row([1024, "3,287,396"]) == "| 1024 | 3,287,396 |"


def test_a_results_header_names_the_date_device_and_command(monkeypatch):
    monkeypatch.setattr("sys.argv", ["benchmarks/env_throughput.py", "--num-envs", "4"])
    header = run_header(torch.device("cpu"))
    assert header["command"] == "python benchmarks/env_throughput.py --num-envs 4"
    assert header["device"] and header["torch"] == torch.__version__
    assert len(header["date"]) == 10 and header["date"][4] == "-"


def test_the_shared_parser_describes_the_script_and_offers_a_device():
    parser = benchmark_parser("Times a thing.\n\n    python benchmarks/x.py --fast\n", device=True)
    assert parser.description == "Times a thing."
    assert "python benchmarks/x.py --fast" in parser.format_help()
    assert parser.parse_args(["--device", "cpu"]).device == "cpu"


def test_field_overrides_parse_literals_and_refuse_unknown_fields_and_non_literals():
    from terrashift_rl.sim import TerraShiftConfig

    parse = field_parser(TerraShiftConfig)
    assert parse("num_objects=1") == ("num_objects", 1)
    assert parse("column_shape='box'") == ("column_shape", "box")
    with pytest.raises(argparse.ArgumentTypeError, match="one of TerraShiftConfig's"):
        parse("bogus=1")
    with pytest.raises(argparse.ArgumentTypeError, match="not a Python literal"):
        parse("num_objects=x")


def test_the_inductor_cache_is_the_folder_torch_compiles_into_with_its_files_counted(
    tmp_path, monkeypatch
):
    from torch._inductor.runtime.cache_dir_utils import cache_dir

    folder = tmp_path / "inductor"
    monkeypatch.setenv("TORCHINDUCTOR_CACHE_DIR", str(folder))
    assert inductor_cache() == {"folder": str(folder), "files": 0}  # not made yet
    (folder / "fxgraph" / "ab").mkdir(parents=True)
    (folder / "fxgraph" / "ab" / "entry").write_bytes(b"graph")
    (folder / "triton").mkdir()
    assert inductor_cache() == {"folder": str(folder), "files": 1}  # files, not folders
    assert inductor_cache()["folder"] == cache_dir()
    monkeypatch.delenv("TORCHINDUCTOR_CACHE_DIR")  # torch's default, which cache_dir() sets
    assert inductor_cache()["folder"] == cache_dir()
