"""train_seeds.py: runs of several seeds side by side, resumed part by part, and summarised."""

import json
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

sys.path.insert(0, str(Path(__file__).parents[2] / "benchmarks"))

import train_seeds  # noqa: E402


def run(monkeypatch, tmp_path: Path, *extra: str) -> None:
    argv = ["train_seeds.py", "--name", "smoke", "--seeds", "0", "1", "--gpus", "0"]
    argv += ["--root", str(tmp_path / "runs"), "--out-dir", str(tmp_path / "summaries"), *extra]
    monkeypatch.setattr(sys, "argv", argv)
    with pytest.raises(SystemExit) as exit_info:
        train_seeds.main()
    assert exit_info.value.code == 0


def test_seeds_run_side_by_side_then_resume_where_they_stopped(monkeypatch, tmp_path):
    run(monkeypatch, tmp_path, "--", "--config-name=smoke")
    summaries = tmp_path / "summaries"
    first = {path.name for path in summaries.glob("*.json")}
    date = json.loads(next(summaries.glob("*.json")).read_text())["date"]
    assert first == {f"cpu_{date}_smoke_seed{seed}.json" for seed in (0, 1)}
    run(monkeypatch, tmp_path, "--resume", "--", "--config-name=smoke", "run.total_env_steps=128")
    for seed in (0, 1):
        before = json.loads((summaries / f"cpu_{date}_smoke_seed{seed}.json").read_text())
        after = json.loads((summaries / f"cpu_{date}_smoke_seed{seed}_part1.json").read_text())
        assert before["steps"][-1] == 64 and after["steps"] == [96, 128]  # it went on from 64
        assert f"run.seed={seed}" in after["overrides"]
        assert any(item.startswith("run.resume=") for item in after["overrides"])
    # the two seeds trained differently
    assert (
        before["series"]["reward_per_decision"]
        != json.loads((summaries / f"cpu_{date}_smoke_seed0.json").read_text())["series"][
            "reward_per_decision"
        ]
    )


def test_resume_without_an_earlier_part_is_refused(monkeypatch, tmp_path, capsys):
    monkeypatch.setattr(
        sys,
        "argv",
        ["train_seeds.py", "--name", "none", "--seeds", "0", "--resume", "--root", str(tmp_path)],
    )
    with pytest.raises(SystemExit):
        train_seeds.main()
    assert "no part of none_seed0" in capsys.readouterr().err


@pytest.mark.parametrize(
    ("name", "prefix"), [("NVIDIA H100 80GB HBM3", "h100"), ("NVIDIA H200", "h200")]
)
def test_device_prefix_names_the_gpu_model(monkeypatch, name, prefix):
    assert train_seeds.device_prefix(torch.device("cpu")) == "cpu"
    monkeypatch.setattr(train_seeds, "device_name", lambda device: name)
    assert train_seeds.device_prefix(torch.device("cuda")) == prefix


def test_a_signal_to_the_launcher_stops_every_run_with_a_checkpoint(tmp_path):
    script = Path(__file__).parents[2] / "benchmarks" / "train_seeds.py"
    command = [sys.executable, str(script), "--name", "long", "--seeds", "0", "1", "--gpus", "0"]
    command += ["--root", str(tmp_path / "runs"), "--out-dir", str(tmp_path / "summaries")]
    command += ["--", "--config-name=smoke", "run.total_env_steps=10000000"]
    launcher = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    checkpoints = [tmp_path / "runs" / f"long_seed{s}_part0" / "checkpoints" for s in (0, 1)]
    deadline = time.monotonic() + 120
    while not all((folder / "last.pt").is_file() for folder in checkpoints):
        assert time.monotonic() < deadline and launcher.poll() is None
        time.sleep(0.5)
    launcher.send_signal(signal.SIGTERM)
    output = launcher.communicate(timeout=120)[0].decode()
    assert launcher.returncode == 0, output
    # each run heard the signal once, finished its iteration, saved, and was summarised
    for folder in checkpoints:
        log = (folder.parent / "train.log").read_text()
        assert log.count("SIGTERM: stopping after this iteration") == 1
        assert "iterations; checkpoint" in log.rsplit("SIGTERM", 1)[1]
    assert len(list((tmp_path / "summaries").glob("cpu_*_long_seed*.json"))) == 2
