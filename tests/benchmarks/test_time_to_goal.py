"""time_to_goal.py: a seed's time to a goal fraction from its logs, evaluation time not counted,
over every part of a resumed run; the recipe's command with a config name; the smoke launch end
to end, stopped at its goal, by Ctrl-C and past its minutes, and resumed; a run past its
deadline after its last line is not counted as cut short."""

import argparse
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).parents[2] / "benchmarks"))

from common import read_evaluations, read_series, run_label, run_parts  # noqa: E402
from time_to_goal import FINAL, logged_last_line, recipe_command, summarize  # noqa: E402

SCRIPT = Path(__file__).parents[2] / "benchmarks" / "time_to_goal.py"


def write_series(folder: Path, metric: str, rows: list[tuple[float, float]]) -> None:
    (folder / f"{metric}.csv").write_text("".join(f"{step},{value}\n" for step, value in rows))


def write_run(folder: Path) -> list[int]:
    """Four iterations of 100 env-steps, 10 s each, with an evaluation of 5 s after the 2nd and
    the 4th: the loop's clock reads 10, 20, 35, 45 s when each iteration ends."""
    steps = [100, 200, 300, 400]
    clock = [10.0, 20.0, 35.0, 45.0]
    write_series(folder, "run_seconds", list(zip(steps, clock, strict=True)))
    write_series(folder, "eval_goal_fraction", [(200, 0.92), (400, 0.96)])
    write_series(folder, "eval_seconds", [(200, 5.0), (400, 5.0)])
    write_series(folder, "eval_out_of_bounds_per_episode", [(200, 0.5), (400, 0.25)])
    write_series(folder, "eval_mean_episode_length", [(200, 300.0), (400, 120.0)])
    write_series(folder, "env_steps_per_s", [(step, 10.0) for step in steps])
    write_series(folder, "collection_steps_per_s", [(step, 50.0) for step in steps])
    write_series(folder, "update_seconds", [(step, 8.0) for step in steps])
    write_series(folder, "estimation_seconds", [(step, 1.0) for step in steps])
    return steps


def test_seconds_to_goal_leave_out_the_evaluations_before(tmp_path):
    write_run(tmp_path)
    entry = summarize(3, tmp_path, [0.95, 0.9, 0.99], launch_seconds=70.0, eval_every=2)
    assert entry["to_goal"]["0.9"] == {"seconds": 20.0, "env_steps": 200}
    assert entry["to_goal"]["0.95"] == {"seconds": 40.0, "env_steps": 400}  # 45 less 5
    assert entry["to_goal"]["0.99"] == {"seconds": None, "env_steps": None}
    assert entry["evaluation_seconds"] == 10.0 and entry["evaluations"] == 2
    assert entry["training_seconds"] == 40.0 and entry["env_steps_per_s"] == 10.0
    assert entry["final_goal_fraction"] == 0.96
    # the metrics logged at the last evaluation, none of those not logged
    assert entry["final_evaluation"] == {
        "out_of_bounds_per_episode": 0.25,
        "mean_episode_length": 120.0,
    }
    assert entry["curve"] == [[200, 20.0, 0.92], [400, 40.0, 0.96]]
    assert (entry["iteration_seconds"], entry["collection_seconds"]) == (10.0, 2.0)
    assert (entry["estimation_seconds"], entry["epochs_seconds"]) == (1.0, 7.0)
    assert "start_scene_goal_fraction" not in entry and "stage_starts" not in entry  # no curriculum


def test_a_result_of_one_seed_is_drawn_as_a_run_of_its_curve(tmp_path):
    write_run(tmp_path)
    entry = summarize(3, tmp_path, [0.9], launch_seconds=70.0, eval_every=2)
    result = tmp_path / "time_to_goal_large_s3.json"
    result.write_text(json.dumps({"device": "cpu", "seeds": [entry]}))
    assert read_series(result, "eval_goal_fraction") == ([200, 400], [0.92, 0.96])
    # the clock of a drawn run's minutes: training seconds, the evaluations not counted
    assert read_series(result, "run_seconds") == ([200, 400], [20.0, 40.0])
    assert read_series(result, "curriculum_stage") == ([], [])  # no curriculum
    assert run_label(result) == "time_to_goal_large_s3" and read_evaluations(result) == {}
    staged = tmp_path / "time_to_goal_staged.json"
    staged.write_text(json.dumps({"seeds": [{**entry, "stage_starts": [300]}]}))
    assert read_series(staged, "curriculum_stage") == ([200, 300, 300, 400], [1, 1, 2, 2])
    several = tmp_path / "time_to_goal_two_seeds.json"
    several.write_text(
        json.dumps({"seeds": [entry, {**entry, "seed": 4, "curve": [[300, 30, 0.5]]}]})
    )
    with pytest.raises(ValueError, match="time_to_goal_two_seeds.json: a time_to_goal result of 2"):
        read_series(several, "eval_goal_fraction")
    # one seed of several, named after a #
    fourth = run_parts(f"{several}#4")[0]
    assert read_series(fourth, "eval_goal_fraction") == ([300], [0.5])
    assert run_label(fourth) == "time_to_goal_two_seeds#4"
    with pytest.raises(
        ValueError, match=r"time_to_goal_two_seeds.json#5: no seed 5 in it \(seeds 3, 4\)"
    ):
        read_series(Path(f"{several}#5"), "eval_goal_fraction")
    summary = tmp_path / "summary.json"
    summary.write_text(json.dumps({"run": "a", "steps": [], "series": {}, "sparse": {}}))
    with pytest.raises(ValueError, match="summary.json is a run summary, not a time_to_goal"):
        read_series(Path(f"{summary}#3"), "eval_goal_fraction")
    with pytest.raises(FileNotFoundError, match="missing.json#3 is neither"):
        run_parts(f"{tmp_path / 'missing.json'}#3")


def test_a_resumed_runs_seconds_leave_out_its_first_parts_final_evaluation(tmp_path):
    write_run(tmp_path)
    # the first part ends by its minutes at 500 env-steps (55 s on its clock) and evaluates
    # once more after its loop (5 s); the second part's clock goes on from its checkpoint's
    # 56 s, and its first iteration ends at 68 s (the compilation included)
    with (tmp_path / "run_seconds.csv").open("a") as file:
        file.write("500,55.0\n600,68.0\n")
    with (tmp_path / "eval_goal_fraction.csv").open("a") as file:
        file.write("500,0.965\n600,0.97\n")
    with (tmp_path / "eval_seconds.csv").open("a") as file:
        file.write("500,5.0\n600,5.0\n")
    entry = summarize(3, tmp_path, [0.97, 0.965], launch_seconds=30.0, eval_every=2)
    # 68 less the in-loop evaluations at 200 and 400: the final one at 500 is off the clock
    assert entry["to_goal"]["0.97"] == {"seconds": 58.0, "env_steps": 600}
    assert entry["to_goal"]["0.965"] == {"seconds": 45.0, "env_steps": 500}
    assert entry["curve"][-2:] == [[500, 45.0, 0.965], [600, 58.0, 0.97]]
    assert entry["training_seconds"] == 58.0 and entry["env_steps_per_s"] == 600 / 58.0


def test_a_run_that_logged_past_the_checkpoint_it_resumed_from_is_refused(tmp_path):
    write_run(tmp_path)
    with (tmp_path / "run_seconds.csv").open("a") as file:  # 300 and 400 logged again
        file.write("300,11.0\n400,21.0\n")
    with pytest.raises(SystemExit, match="env-steps twice"):
        summarize(3, tmp_path, [0.95], launch_seconds=30.0, eval_every=2)


def test_a_curriculum_runs_entry_keeps_the_last_scores_of_its_stages(tmp_path):
    steps = write_run(tmp_path)
    write_series(tmp_path, "curriculum_stage", [(step, 1.0 + (step > 200)) for step in steps])

    def kept() -> tuple[float | None, float | None]:
        entry = summarize(3, tmp_path, [0.9], launch_seconds=70.0, eval_every=2)
        return entry["start_scene_goal_fraction"], entry["stage_goal_fraction"]

    assert kept() == (None, None)
    write_series(tmp_path, "curriculum_eval_goal_fraction", [(100, 0.4), (200, 0.82)])
    write_series(tmp_path, "curriculum_start_eval_goal_fraction", [(300, 0.97), (400, 0.95)])
    assert kept() == (0.95, 0.82)


def test_a_curriculum_runs_entry_keeps_where_each_stage_began(tmp_path):
    write_run(tmp_path)
    write_series(tmp_path, "curriculum_stage", [(100, 1.0), (200, 2.0), (300, 2.0), (400, 3.0)])
    entry = summarize(3, tmp_path, [0.9], launch_seconds=70.0, eval_every=2)
    assert entry["stage_starts"] == [200, 400]


@pytest.mark.slow
def test_the_smoke_setting_runs_two_seeds_on_the_cpu(tmp_path):
    out = tmp_path / "time_to_goal.json"
    command = [sys.executable, str(SCRIPT), "--smoke", "--seeds", "0", "1", "--minutes", "0.1"]
    cache = tmp_path / "inductor"  # empty: the runs' compilation would start afresh
    result = subprocess.run(
        [*command, "--eval-every", "1", "--thresholds", "0", "--out", str(out)],
        capture_output=True,
        text=True,
        timeout=600,
        env={**os.environ, "TORCHINDUCTOR_CACHE_DIR": str(cache)},
    )
    assert result.returncode == 0, result.stderr
    payload = json.loads(out.read_text())
    assert payload["inductor_cache"] == {"folder": str(cache), "files": 0}
    assert [seed["seed"] for seed in payload["seeds"]] == [0, 1]
    # a goal fraction of at least 0 is reached at the first evaluation, after one iteration
    frames = 4 * 8
    assert all(seed["to_goal"]["0"]["env_steps"] == frames for seed in payload["seeds"])
    assert payload["median_seconds_to_goal"] > 0 and payload["seeds_at_goal"] == 2
    assert payload["env_steps_per_s"] > 0 and "mapoca_pretrain.py" in payload["recipe_command"]
    # every seed keeps its last evaluation's metrics, and its row prints them
    assert all(set(seed["final_evaluation"]) == set(FINAL) for seed in payload["seeds"])
    assert " lost, " in result.stdout and " decisions |" in result.stdout


def run_one_seed(tmp_path: Path, *options: str) -> tuple[dict, Path]:
    """Runs the smoke benchmark for seed 0, evaluating every iteration, no grace, with
    ``options``; its seed's entry and the folder that keeps its run."""
    out, keep = tmp_path / "time_to_goal.json", tmp_path / "runs"
    command = [sys.executable, str(SCRIPT), "--smoke", "--seeds", "0", "--eval-every", "1"]
    result = subprocess.run(
        [*command, "--grace", "0", *options, "--out", str(out), "--keep", str(keep)],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert result.returncode == 0, result.stderr
    (seed,) = json.loads(out.read_text())["seeds"]
    return seed, keep


@pytest.mark.slow
@pytest.mark.parametrize("processes", [1, 2])  # 2: under torchrun (gloo)
def test_stop_at_goal_interrupts_a_seed_at_its_first_evaluation_past_every_threshold(
    tmp_path, processes
):
    options = ["--minutes", "10", "--processes", str(processes), "--thresholds", "0"]
    seed, keep = run_one_seed(tmp_path, *options, "--stop-at-goal")
    # stopped long before its 10 minutes, as Ctrl-C stops a run: with its checkpoint
    assert seed["to_goal"]["0"]["env_steps"] == processes * 4 * 8
    assert seed["launch_seconds"] < 300
    assert (keep / "seed_0" / "checkpoints" / "last.pt").is_file()
    assert "run.resume=seed_0/checkpoints/last.pt" in (keep / "seed_0.log").read_text()


def ignore_sigint() -> None:
    """As a shell without job control starts a background job: SIGINT ignored."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)


@pytest.mark.slow
@pytest.mark.parametrize("stop", [signal.SIGINT, signal.SIGTERM])
def test_ctrl_c_writes_what_the_running_seed_logged_and_exits_130(tmp_path, stop):
    out, keep = tmp_path / "time_to_goal.json", tmp_path / "runs"
    command = [sys.executable, str(SCRIPT), "--smoke", "--seeds", "0", "--minutes", "10"]
    command += ["--eval-every", "1", "--thresholds", "0.99", "--grace", "0"]
    benchmark = subprocess.Popen(
        [*command, "--out", str(out), "--keep", str(keep)],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        preexec_fn=ignore_sigint,  # a background job: the benchmark must catch SIGINT itself
    )
    evaluations = keep / "seed_0" / "logs" / "smoke" / "scalars" / "eval_goal_fraction.csv"
    deadline = time.monotonic() + 300  # a hang guard: the first evaluation comes within seconds
    while not (evaluations.is_file() and evaluations.read_text()) and time.monotonic() < deadline:
        time.sleep(0.5)
    benchmark.send_signal(stop)  # as Ctrl-C in a terminal, or a scheduler, reaches the benchmark
    output, _ = benchmark.communicate(timeout=300)
    assert benchmark.returncode == 130, output
    payload = json.loads(out.read_text())
    (seed,) = payload["seeds"]
    assert payload["interrupted"] and seed["interrupted"] and seed["evaluations"] >= 1
    assert (keep / "seed_0" / "checkpoints" / "last.pt").is_file()  # stopped as Ctrl-C stops it


@pytest.mark.slow
def test_a_seed_past_its_minutes_and_grace_is_stopped_and_kept(tmp_path):
    start = time.monotonic()
    # the run itself would train for 10 minutes: the benchmark stops it after its half minute
    options = ["--minutes", "0.5", "--thresholds", "0.99", "--overrides", "run.minutes=10"]
    seed, keep = run_one_seed(tmp_path, *options)
    assert time.monotonic() - start < 300
    assert seed["interrupted"] and seed["evaluations"] >= 1
    assert (keep / "seed_0" / "checkpoints" / "last.pt").is_file()  # stopped as Ctrl-C stops it


@pytest.mark.slow
def test_resume_goes_on_with_a_kept_run_and_its_clock(tmp_path):
    out, keep = tmp_path / "time_to_goal.json", tmp_path / "runs"
    command = [sys.executable, str(SCRIPT), "--smoke", "--seeds", "0", "--minutes", "0.1"]
    command += ["--eval-every", "1", "--thresholds", "0.99", "--out", str(out), "--keep", str(keep)]

    def one_part(*options: str) -> dict:
        result = subprocess.run([*command, *options], capture_output=True, text=True, timeout=600)
        assert result.returncode == 0, result.stderr
        (seed,) = json.loads(out.read_text())["seeds"]
        return seed

    first = one_part()
    first_part = (keep / "seed_0.log").stat().st_size
    second = one_part("--resume")
    assert json.loads(out.read_text())["resumed"]
    assert second["env_steps"] > first["env_steps"]
    assert second["training_seconds"] > first["training_seconds"]
    assert second["curve"][: len(first["curve"])] == first["curve"]
    clock = keep / "seed_0" / "logs" / "smoke" / "scalars" / "run_seconds.csv"
    seconds = [float(row.split(",")[1]) for row in clock.read_text().split()]
    assert len(seconds) > len(first["curve"]) and seconds == sorted(seconds)  # one clock
    log = (keep / "seed_0.log").read_text()  # both parts' output
    assert log.count("env-steps in") == 2 and "run.resume=" in log
    # the recipe's last line, which tells a run slow to exit from one cut short, in the second
    assert logged_last_line(keep / "seed_0.log", part_start=first_part)


def test_only_the_current_parts_last_line_counts(tmp_path):
    log = tmp_path / "seed_0.log"
    first = "1,024 env-steps in 2 iterations; checkpoint seed_0/checkpoints/last.pt (0.1 minutes)\n"
    log.write_text(first + "mapoca_pretrain:  50%|█████     | 1.5k/3.1k\n")
    assert logged_last_line(log, part_start=0)
    assert not logged_last_line(log, part_start=len(first.encode()))  # resumed, not over yet


def test_resume_needs_the_kept_runs_and_names_a_seed_without_a_checkpoint(tmp_path):
    command = [sys.executable, str(SCRIPT), "--smoke", "--seeds", "0", "1", "--resume"]
    result = subprocess.run(command, capture_output=True, text=True, timeout=120)
    assert result.returncode == 2 and "name that folder" in result.stderr
    (tmp_path / "seed_0" / "checkpoints").mkdir(parents=True)
    (tmp_path / "seed_0" / "checkpoints" / "last.pt").touch()
    result = subprocess.run(
        [*command, "--keep", str(tmp_path)], capture_output=True, text=True, timeout=120
    )
    assert result.returncode == 2 and "for seed(s) 1" in result.stderr


def test_a_config_name_reaches_the_recipe_and_not_beside_smoke():
    args = argparse.Namespace(
        processes=1,
        minutes=1.0,
        eval_every=5,
        smoke=False,
        config_name="mapoca_pixels",
        resume=False,
    )
    args.overrides = ["env.camera_resolution=32"]
    command = recipe_command(7, args, Path("run"))
    at = command.index("--config-name")
    assert command[at + 1] == "mapoca_pixels" and command[-2] == "env.camera_resolution=32"
    result = subprocess.run(
        [sys.executable, str(SCRIPT), "--smoke", "--config-name", "mapoca_pixels"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert result.returncode == 2 and "leave out --config-name" in result.stderr
