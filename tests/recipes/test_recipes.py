"""Recipes: every config composes; the smoke config trains, resumes exactly and finetunes."""

import json
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir
from PIL import Image
from tqdm import tqdm

ROOT = Path(__file__).resolve().parents[2]
RECIPES = ROOT / "recipes"
CONFIGS = RECIPES / "configs"
sys.path.insert(0, str(RECIPES))
import mapoca_pretrain  # noqa: E402  (also registers the env and model groups' schemas)

PRIMARY = sorted(path.stem for path in CONFIGS.glob("*.yaml"))


def group_options() -> list[tuple[str, str]]:
    """Every option of every config group, found by searching the folder recursively."""
    return sorted(
        (path.parent.relative_to(CONFIGS).as_posix(), path.stem)
        for path in CONFIGS.rglob("*.yaml")
        if path.parent != CONFIGS
    )


@pytest.mark.parametrize("name", PRIMARY)
def test_primary_configs_compose(name):
    with initialize_config_dir(config_dir=str(CONFIGS), version_base=None):
        cfg = compose(config_name=name)
    assert "env" in cfg
    if "run" in cfg:  # a training recipe
        assert {"model", "train", "loss", "logger"} <= set(cfg)


@pytest.mark.parametrize(("group", "option"), group_options())
def test_every_group_option_composes_into_its_dataclass(group, option):
    from terrashift_rl.modules import TerraShiftModelConfig
    from terrashift_rl.sim import TerraShiftConfig
    from terrashift_rl.training import TrainConfig

    with initialize_config_dir(config_dir=str(CONFIGS), version_base=None):
        cfg = compose(config_name="mapoca_pretrain", overrides=[f"{group}={option}"])
    values = dict(cfg[group])
    if group == "env":
        TerraShiftConfig(**values)
    elif group == "model":
        TerraShiftModelConfig(**values)
    elif group in ("train", "loss"):
        TrainConfig(**values).validate()
    else:
        assert values["kind"] in ("wandb", "csv", "tensorboard", "none")


def test_default_train_and_loss_groups_are_train_config_defaults():
    """The recipe's defaults and the library's TrainConfig() are the same measured setting."""
    from terrashift_rl.training import TrainConfig

    with initialize_config_dir(config_dir=str(CONFIGS), version_base=None):
        cfg = compose(config_name="mapoca_pretrain")
    assert TrainConfig(**{**cfg.train, **cfg.loss}) == TrainConfig()


def run(
    script: str, *overrides: str, cwd: Path, config_name: str | None = "smoke"
) -> subprocess.CompletedProcess:
    """Runs a recipe in a subprocess (with the smoke config unless told otherwise)."""
    config = [] if config_name is None else ["--config-name", config_name]
    return subprocess.run(
        [sys.executable, str(RECIPES / script), *config, *overrides],
        cwd=cwd,
        capture_output=True,
        text=True,
        timeout=600,
    )


def test_smoke_train_resume_and_finetune(tmp_path):
    straight = run("mapoca_pretrain.py", "run.total_env_steps=96", "hydra.run.dir=a", cwd=tmp_path)
    assert straight.returncode == 0, straight.stderr
    first = run("mapoca_pretrain.py", "run.total_env_steps=32", "hydra.run.dir=b", cwd=tmp_path)
    assert first.returncode == 0, first.stderr
    resumed = run(
        "mapoca_pretrain.py",
        "run.total_env_steps=96",
        "run.resume=b/checkpoints/last.pt",
        "hydra.run.dir=c",
        cwd=tmp_path,
    )
    assert resumed.returncode == 0, resumed.stderr
    a = torch.load(tmp_path / "a/checkpoints/last.pt", weights_only=False)
    c = torch.load(tmp_path / "c/checkpoints/last.pt", weights_only=False)
    assert a["iteration"] == c["iteration"] == 3
    # a killed-and-resumed run continues exactly where the straight run went
    for name, value in a["networks"].items():
        torch.testing.assert_close(c["networks"][name], value, atol=0, rtol=0)

    finetune = run(
        "mapoca_finetune.py",
        "run.pretrained=b/checkpoints/last.pt",
        "env.grid_size=10",
        "env.num_agents=6",
        "model.policy_output_gain=0.5",  # initial weights, which the pretrained ones replace
        "hydra.run.dir=d",
        cwd=tmp_path,
    )
    assert finetune.returncode == 0, finetune.stderr
    d = torch.load(tmp_path / "d/checkpoints/last.pt", weights_only=False)
    assert d["env_config"]["num_agents"] == 6 and d["iteration"] == 2

    evaluation = run(
        "evaluate.py",
        "checkpoint=d/checkpoints/last.pt",
        "episodes=3",
        "device=cpu",
        "video.steps=2",
        "video.every=1",
        "video.format=gif",
        "hydra.run.dir=e",
        cwd=tmp_path,
        config_name=None,
    )
    assert evaluation.returncode == 0, evaluation.stderr
    report = json.loads((tmp_path / "e/evaluation.json").read_text())
    assert report["scene"]["num_agents"] == 6 and not report["scene"]["respawn"]
    for name in ("deterministic", "stochastic"):
        assert report[name]["episodes"] == 3
        assert 0.0 <= report[name]["success_rate"] <= 1.0
    assert set(report["baselines"]) == {"random", "zero", "heuristic"}
    with Image.open(tmp_path / "e/rollout.gif") as video:
        assert video.n_frames >= 2  # the reset frame and one per decision (GIFs merge repeats)


def test_a_terminated_run_checkpoints_a_whole_iteration(tmp_path):
    # SIGTERM lands mid-iteration more often than not; the run finishes that iteration first,
    # so its checkpoint equals that of a run told to stop there
    command = [sys.executable, str(RECIPES / "mapoca_pretrain.py"), "--config-name", "smoke"]
    killed = subprocess.Popen(
        [*command, "run.total_env_steps=1000000", "run.checkpoint_every=1", "hydra.run.dir=k"],
        cwd=tmp_path,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    deadline = time.monotonic() + 300
    while not (tmp_path / "k/checkpoints/last.pt").exists() and time.monotonic() < deadline:
        time.sleep(0.1)
    time.sleep(1.0)
    killed.send_signal(signal.SIGTERM)
    stdout, stderr = killed.communicate(timeout=300)
    assert killed.returncode == 0, stderr
    assert "SIGTERM: stopping after this iteration" in stdout
    k = torch.load(tmp_path / "k/checkpoints/last.pt", weights_only=False)
    straight = run(
        "mapoca_pretrain.py",
        f"run.total_env_steps={k['env_steps']}",
        "hydra.run.dir=s",
        cwd=tmp_path,
    )
    assert straight.returncode == 0, straight.stderr
    s = torch.load(tmp_path / "s/checkpoints/last.pt", weights_only=False)
    assert s["iteration"] == k["iteration"]
    for name, value in s["networks"].items():
        torch.testing.assert_close(k["networks"][name], value, atol=0, rtol=0)
    torch.testing.assert_close(k["simulator"], s["simulator"], atol=0, rtol=0)


def test_a_second_signal_interrupts_at_once():
    before = {number: signal.getsignal(number) for number in (signal.SIGINT, signal.SIGTERM)}
    with mapoca_pretrain.StopRequest(tqdm(disable=True)) as stop:
        assert signal.getsignal(signal.SIGTERM) is stop
        stop(signal.SIGTERM, None)
        assert stop.requested
        with pytest.raises(KeyboardInterrupt):
            stop(signal.SIGINT, None)
    assert {number: signal.getsignal(number) for number in before} == before


def test_best_checkpoint_and_snapshots_hold_the_weights_they_name(tmp_path):
    result = run(
        "mapoca_pretrain.py",
        "run.total_env_steps=128",
        "run.best_window=2",
        "run.snapshot_every=2",
        "logger=csv",
        "hydra.run.dir=a",
        cwd=tmp_path,
    )
    assert result.returncode == 0, result.stderr
    logged = (tmp_path / "a/logs/smoke/scalars/reward_per_decision.csv").read_text().split()
    rows = [row.split(",") for row in logged]
    steps, rewards = [int(step) for step, _ in rows], [float(reward) for _, reward in rows]
    means = [(rewards[i - 1] + rewards[i]) / 2 for i in range(1, len(rewards))]
    best_index = max(range(len(means)), key=means.__getitem__)
    best = torch.load(tmp_path / "a/checkpoints/best.pt", weights_only=False)
    assert len(rewards) == 4
    assert best["mean_reward_per_decision"] == pytest.approx(means[best_index], rel=1e-6)
    assert best["env_steps"] == steps[best_index + 1]
    assert best["iteration"] == best_index + 2
    last = torch.load(tmp_path / "a/checkpoints/last.pt", weights_only=False)
    assert last["best"]["reward"] == best["mean_reward_per_decision"]
    assert last["best"]["recent"] == pytest.approx(rewards[-2:], rel=1e-6)
    # a snapshot every 2 iterations: the weights and counters of that iteration
    snapshots = sorted(path.name for path in (tmp_path / "a/checkpoints").glob("iteration_*.pt"))
    assert snapshots == ["iteration_000002.pt", "iteration_000004.pt"]
    second = torch.load(tmp_path / "a/checkpoints/iteration_000002.pt", weights_only=False)
    assert (second["iteration"], second["env_steps"]) == (2, steps[1])
    fourth = torch.load(tmp_path / "a/checkpoints/iteration_000004.pt", weights_only=False)
    for name, value in last["networks"].items():
        torch.testing.assert_close(fourth["networks"][name], value, atol=0, rtol=0)
    assert any(
        not torch.equal(second["networks"][name], value) for name, value in last["networks"].items()
    )
    # best.pt is what evaluate.py and finetuning read; here scored in training mode
    evaluation = run(
        "evaluate.py",
        "checkpoint=a/checkpoints/best.pt",
        "episodes=2",
        "device=cpu",
        "video.steps=0",
        "baselines=false",
        "respawn=true",
        "hydra.run.dir=e",
        cwd=tmp_path,
        config_name=None,
    )
    assert evaluation.returncode == 0, evaluation.stderr
    report = json.loads((tmp_path / "e/evaluation.json").read_text())
    assert report["checkpoint_env_steps"] == best["env_steps"]
    assert report["scene"]["respawn"]
    for name in ("deterministic", "stochastic"):  # every episode runs to the step limit
        assert report[name]["mean_episode_length"] == best["env_config"]["max_episode_steps"]
    # the same weights, from the last checkpoint and from its snapshot: with the same seed the
    # sampled actions, and so every score, are the same
    sampled = []
    for source in ("last", "iteration_000004"):
        evaluation = run(
            "evaluate.py",
            f"checkpoint=a/checkpoints/{source}.pt",
            "episodes=2",
            "device=cpu",
            "video.steps=0",
            "baselines=false",
            "respawn=true",
            f"hydra.run.dir={source}",
            cwd=tmp_path,
            config_name=None,
        )
        assert evaluation.returncode == 0, evaluation.stderr
        sampled.append(
            json.loads((tmp_path / source / "evaluation.json").read_text())["stochastic"]
        )
    assert sampled[0] == sampled[1]


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        (["train.minibatches=99"], "minibatches"),
        (["run.best_window=-1"], "run.best_window"),
        (["run.snapshot_every=0"], "run.snapshot_every"),
        (["+env.grid_sise=10"], "unknown key"),
        (["run.resume=missing.pt"], "no checkpoint at"),
        (["logger.kind=paper"], "logger.kind"),
    ],
)
def test_bad_configuration_fails_at_start_up(tmp_path, overrides, message):
    result = run("mapoca_pretrain.py", *overrides, "hydra.run.dir=x", cwd=tmp_path)
    assert result.returncode != 0
    assert message in result.stderr


def test_evaluate_rejects_a_respawn_that_is_not_a_boolean(tmp_path):
    result = run(
        "evaluate.py", "respawn=sometimes", "hydra.run.dir=x", cwd=tmp_path, config_name=None
    )
    assert result.returncode != 0
    assert "respawn must be false (evaluation mode) or true (training mode)" in result.stderr


def test_resume_ignores_settings_that_only_set_the_initial_weights():
    with initialize_config_dir(config_dir=str(CONFIGS), version_base=None):
        cfg = compose(config_name="smoke")
    configs = {
        "env_config": {"grid_size": 15},
        "model_config": {"embed_dim": 32, "policy_output_gain": 0.01},
        "train_config": {"minibatches": 2},
    }
    for saved_model in ({"embed_dim": 32, "policy_output_gain": 1.0}, {"embed_dim": 32}):
        mapoca_pretrain.check_resumable({**configs, "model_config": saved_model}, configs, cfg)
    wider = {**configs, "model_config": {"embed_dim": 64, "policy_output_gain": 0.01}}
    with pytest.raises(ValueError, match="add model.embed_dim=64 to continue"):
        mapoca_pretrain.check_resumable(wider, configs, cfg)


def test_resume_names_the_settings_that_differ_from_the_checkpoints(tmp_path):
    first = run("mapoca_pretrain.py", "train.minibatches=1", "hydra.run.dir=b", cwd=tmp_path)
    assert first.returncode == 0, first.stderr
    result = run(
        "mapoca_pretrain.py",
        "run.resume=b/checkpoints/last.pt",
        "model.embed_dim=64",
        "loss.gamma=0.9",
        "+train.compile=true",  # how the networks execute may change
        "hydra.run.dir=y",
        cwd=tmp_path,
    )
    assert result.returncode != 0
    assert "add model.embed_dim=32 train.minibatches=1 loss.gamma=0.95 to continue" in (
        result.stderr
    )
