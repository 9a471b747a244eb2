"""Recipes: every config composes into the settings room; the smoke config trains, resumes exactly
and finetunes; without CUDA, run.device=auto sizes a run for the CPU. The subprocess runs are
marked slow."""

import dataclasses
import importlib.util
import json
import os
import shlex
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir
from hydra.errors import ConfigCompositionException
from omegaconf import OmegaConf
from PIL import Image

from terrashift_rl.modules import TerraShiftModelConfig
from terrashift_rl.sim import TerraShiftConfig
from terrashift_rl.training import ALGORITHMS, TrainConfig, load_checkpoint
from terrashift_rl.training.checkpoint import STALE_AFTER_S, check_resumable, upgrade
from terrashift_rl.training.settings import EvaluateConfig, RecipeConfig, RunConfig

ROOT = Path(__file__).resolve().parents[2]
RECIPES = ROOT / "recipes"
CONFIGS = RECIPES / "configs"
spec = importlib.util.spec_from_file_location("mapoca_pretrain", RECIPES / "mapoca_pretrain.py")
pretrain = importlib.util.module_from_spec(spec)
spec.loader.exec_module(pretrain)  # registers the config schemas

PRIMARY = sorted(path.stem for path in CONFIGS.glob("*.yaml"))
PAPER_INCANTATION = (
    "model=table1 train=table1 loss=table1 env.respawn_fraction=1 env.approach_scale=0 "
    "env.action_mode=delta"
)


def compose_config(name: str, *overrides: str):
    with initialize_config_dir(config_dir=str(CONFIGS), version_base=None):
        return compose(config_name=name, overrides=list(overrides))


def group_options() -> list[tuple[str, str]]:
    """Every option of every config group, found by searching the folder recursively."""
    return sorted(
        (path.parent.relative_to(CONFIGS).as_posix(), path.stem)
        for path in CONFIGS.rglob("*.yaml")
        if path.parent != CONFIGS
    )


@pytest.mark.parametrize("name", PRIMARY)
def test_primary_configs_compose(name):
    cfg = compose_config(name)
    assert "env" in cfg
    if "run" in cfg:  # a training recipe
        assert RecipeConfig.of(cfg).run.name == name


@pytest.mark.parametrize(("group", "option"), group_options())
def test_every_group_option_composes_into_its_dataclass(group, option):
    settings = RecipeConfig.of(compose_config("mapoca_pretrain", f"{group}={option}"))
    if group == "algo":
        assert settings.train.algo == option
        assert type(settings.train.loss) is ALGORITHMS[option]


def test_the_groups_default_to_their_settings_classes_defaults():
    settings = RecipeConfig.of(compose_config("mapoca_pretrain", "model=table1"))
    # train=default is TrainConfig's, with compiled networks (off in the settings class, which
    # also serves CPU-sized and library use), 8,192 environments of 8 decisions and twice the
    # learning rates over 300-iteration schedules (the class keeps 2,048 of 32 at 1e-3 over
    # 1,000, on which train=table1 and train=throughput build)
    assert settings.train == dataclasses.replace(
        TrainConfig(),
        compile=True,
        num_envs=8192,
        steps_per_iteration=8,
        lr_trunk_policy=2e-3,
        lr_value_baseline=1.2e-3,
        schedule_iterations=300,
    )
    assert settings.model == TerraShiftModelConfig()
    assert settings.run == RunConfig()
    assert set(compose_config("mapoca_pretrain").loss) == {
        "algo",
        *(field.name for field in dataclasses.fields(ALGORITHMS["mapoca"])),
    }


def test_the_paper_config_is_table_1():
    cfg = compose_config("mapoca_paper")
    settings = RecipeConfig.of(cfg)
    # the same as the six overrides it replaces
    incantation = RecipeConfig.of(compose_config("mapoca_pretrain", *PAPER_INCANTATION.split()))
    assert dataclasses.replace(settings, run=incantation.run) == incantation
    assert settings.env == TerraShiftConfig()  # the paper's scene and reward
    assert settings.model == TerraShiftModelConfig()
    config, loss = settings.train, settings.train.loss
    # 8,192 decisions per update in sequences of 32, mini-batches of 32 sequences, 4 epochs
    assert config.num_envs * config.steps_per_iteration == 8 * 1024
    assert config.steps_per_iteration == 32
    assert config.num_envs // config.minibatches == 32
    assert config.epochs == 4
    assert (loss.gamma, loss.lmbda) == (0.95, 0.92)
    assert (config.lr_trunk_policy, config.lr_value_baseline) == (1e-4, 2e-4)
    assert (config.lr_schedule, config.lr_end_factor, config.weight_decay) == ("linear", 0.1, 0.0)
    assert config.schedule_iterations == 10_000
    assert (loss.clip_epsilon_start, loss.clip_epsilon_end) == (0.2, 0.1)
    assert (loss.entropy_coeff_start, loss.entropy_coeff_end) == (0.005, 0.001)
    assert (config.max_grad_norm_start, config.max_grad_norm_end) == (5.0, 0.5)


def test_the_six_override_incantation_is_written_nowhere_but_here():
    tracked = subprocess.run(
        ["git", "ls-files", "recipes", "terrashift_rl", "tests", "docs/tutorials", "examples"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        check=True,
    ).stdout.split()
    written = [
        path
        for path in tracked
        if path != "tests/recipes/test_recipes.py"
        and (ROOT / path).is_file()
        and "train=table1 loss=table1" in (ROOT / path).read_text(errors="ignore")
    ]
    assert written == []


def test_the_finetune_recipe_differs_from_pretraining_in_its_scene_warm_up_and_kl_bound():
    pretrain_settings = RecipeConfig.of(compose_config("mapoca_pretrain"))
    finetune = RecipeConfig.of(compose_config("mapoca_finetune"))
    assert (finetune.env.grid_size, finetune.env.num_agents) == (30, 16)
    assert finetune.env.action_mode == pretrain_settings.env.action_mode  # the checkpoint's
    config = finetune.train
    # the critics fit the new scene for 0.5 M env-steps before the policy moves, then the
    # policy's rate follows a KL target below the adaptive schedule's default
    assert config.critic_warmup_iterations * config.num_envs * config.steps_per_iteration >= 5e5
    assert config.lr_schedule == "adaptive" and config.desired_kl < TrainConfig().desired_kl
    assert not config.compile  # runs of minutes: no first compilation
    changed = {"compile", "critic_warmup_iterations", "lr_schedule", "desired_kl"}
    expected = dataclasses.replace(
        pretrain_settings.train, **{name: getattr(config, name) for name in changed}
    )
    assert config == expected
    assert finetune.model == pretrain_settings.model


def test_the_pretraining_recipe_alone_compiles_its_networks():
    # the main job's runs repay a first compilation of minutes; finetuning runs for minutes and
    # the pixel recipe's compiled camera stem is unmeasured; smoke and Table 1 use train groups
    # of their own
    names = ("mapoca_pretrain", "mapoca_finetune", "mapoca_pixels", "mapoca_paper", "smoke")
    compiled = {name: RecipeConfig.of(compose_config(name)).train.compile for name in names}
    assert compiled == {name: name == "mapoca_pretrain" for name in names}


@pytest.mark.parametrize(
    "path",
    sorted(
        path
        for group in ("env", "model", "train", "algo", "logger")
        for path in (CONFIGS / group).glob("*.yaml")
    ),
    ids=lambda path: f"{path.parent.name}/{path.stem}",
)
def test_a_group_file_sets_only_what_differs_from_its_schema(path):
    """A file that repeats a schema default would be a second place to change it."""
    group = path.parent.name
    values = OmegaConf.to_container(OmegaConf.load(path))
    schema, last = values.pop("defaults")
    assert schema.endswith("schema") or schema == "schema_small"
    assert last == "_self_"
    node = "loss" if group == "algo" else group
    cfg = compose_config("mapoca_pretrain", f"{group}={path.stem}")
    with initialize_config_dir(config_dir=str(CONFIGS), version_base=None):
        defaults = compose(config_name="mapoca_pretrain", overrides=[f"{group}={schema}"])
    repeated = sorted(key for key, value in values.items() if defaults[node][key] == value)
    assert not repeated, f"{path.name} repeats the schema's defaults of {repeated}"
    assert all(cfg[node][key] == value for key, value in values.items())


@pytest.mark.parametrize(
    ("override", "message"),
    [
        ("train.nope=1", "Key 'nope' is not in struct"),
        ("loss.nope=1", "Key 'nope' is not in struct"),
        ("train.gamma=0.9", "Key 'gamma' is not in struct"),  # a loss setting
        ("loss.num_envs=8", "Key 'num_envs' is not in struct"),  # a train setting
        ("loss.teacher_coeff=1", "Key 'teacher_coeff' is not in struct"),  # with algo=mappo
    ],
)
def test_hydra_refuses_a_key_the_group_lacks(override, message):
    with pytest.raises(ConfigCompositionException) as error:
        compose_config("mapoca_pretrain", "algo=mappo", override)
    assert override.split("=")[0] in str(error.value)  # the key as the command line gave it
    assert message in str(error.value.__cause__)


@pytest.mark.parametrize(
    ("override", "message"),
    [
        ("train.num_envs=many", "^train.num_envs must be an integer >= 1, got 'many'$"),
        ("loss.normalize_value=maybe", "^loss.normalize_value must be true or false, got 'maybe'"),
        ("+loss.nope=1", "^loss.nope is not a setting of algo=mapoca"),
    ],
)
def test_the_room_refuses_a_value_of_the_wrong_type_or_an_added_key(override, message):
    with pytest.raises(ValueError, match=message):
        RecipeConfig.of(compose_config("mapoca_pretrain", override))


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


CURRICULUM = (
    "curriculum=auto",
    "curriculum.start_grid_size=6",
    "curriculum.start_num_agents=2",
    "curriculum.start_num_objects=1",
    "curriculum.threshold=0",  # advance at every evaluation of the stage
)


def test_a_curriculum_run_advances_a_stage_and_checkpoints_it(tmp_path):
    result = run(
        "mapoca_pretrain.py",
        *CURRICULUM,
        "curriculum.stages=2",
        "curriculum.eval_every=1",
        "curriculum.retention_every=1",
        "run.total_env_steps=64",
        "hydra.run.dir=a",
        cwd=tmp_path,
    )
    assert result.returncode == 0, result.stderr
    assert "stage 2/2: 8x8 columns, 4 agents, 2 spheres from 32 env-steps" in result.stdout
    # at the target, the first stage's scene is scored again (every iteration here)
    assert "stage 1's scene at 32 env-steps" not in result.stdout
    assert "stage 1's scene at 64 env-steps: goal fraction" in result.stdout
    saved = load_checkpoint(tmp_path / "a/checkpoints/last.pt")
    assert saved["curriculum"] == {"stage": 1, "advances": [32], "scenes": [[6, 2, 1], [8, 4, 2]]}
    assert saved["carry"]["agents", "mask"].shape[-1] == 4  # padded to the second stage's agents
    assert saved["curriculum_config"]["kind"] == "auto"


@pytest.mark.slow
def test_a_curriculum_run_killed_mid_stage_resumes_exactly(tmp_path):
    stages = (*CURRICULUM, "curriculum.stages=3", "curriculum.eval_every=2")
    straight = run(
        "mapoca_pretrain.py", *stages, "run.total_env_steps=160", "hydra.run.dir=a", cwd=tmp_path
    )
    assert straight.returncode == 0, straight.stderr
    first = run(
        "mapoca_pretrain.py", *stages, "run.total_env_steps=96", "hydra.run.dir=b", cwd=tmp_path
    )
    assert first.returncode == 0, first.stderr
    killed = load_checkpoint(tmp_path / "b/checkpoints/last.pt")
    assert killed["curriculum"]["stage"] == 1 and killed["carry"] is not None  # mid-stage
    resumed = run(
        "mapoca_pretrain.py",
        *stages,
        "run.total_env_steps=160",
        "run.resume=b/checkpoints/last.pt",
        "hydra.run.dir=c",
        cwd=tmp_path,
    )
    assert resumed.returncode == 0, resumed.stderr
    a = load_checkpoint(tmp_path / "a/checkpoints/last.pt")
    c = load_checkpoint(tmp_path / "c/checkpoints/last.pt")
    assert a["curriculum"] == c["curriculum"]
    assert a["curriculum"]["advances"] == [64, 128]
    for name, value in a["networks"].items():
        torch.testing.assert_close(c["networks"][name], value, atol=0, rtol=0)


@pytest.mark.slow
def test_smoke_train_resume_and_finetune(tmp_path):
    straight = run("mapoca_pretrain.py", "run.total_env_steps=96", "hydra.run.dir=a", cwd=tmp_path)
    assert straight.returncode == 0, straight.stderr
    # 3 iterations, an evaluation every 4: the bar's last state shows the final evaluation's score
    bars = [line for line in straight.stderr.splitlines() if "eval_goals=" in line]
    assert "eval_goals=-" in bars[0] and "eval_goals=0." in bars[-1]
    first = run("mapoca_pretrain.py", "run.total_env_steps=32", "hydra.run.dir=b", cwd=tmp_path)
    assert first.returncode == 0, first.stderr
    # as a kill during a checkpoint's write leaves it; the resumed run removes it
    stale = tmp_path / "b/checkpoints/.last.pt.killed.tmp"
    stale.write_bytes(b"half a checkpoint")
    os.utime(stale, (time.time() - 2 * STALE_AFTER_S,) * 2)
    resumed = run(
        "mapoca_pretrain.py",
        "run.total_env_steps=96",
        "run.resume=b/checkpoints/last.pt",
        "hydra.run.dir=c",
        cwd=tmp_path,
    )
    assert resumed.returncode == 0, resumed.stderr
    assert not stale.exists() and f"removed {stale.relative_to(tmp_path)}" in resumed.stdout
    a = load_checkpoint(tmp_path / "a/checkpoints/last.pt")
    c = load_checkpoint(tmp_path / "c/checkpoints/last.pt")
    assert a["iteration"] == c["iteration"] == 3
    # a killed-and-resumed run continues exactly where the straight run went
    for name, value in a["networks"].items():
        torch.testing.assert_close(c["networks"][name], value, atol=0, rtol=0)

    finetune = run(
        "mapoca_finetune.py",
        "run.pretrained=b/checkpoints/last.pt",
        "env.grid_size=10",
        "env.num_agents=6",
        "model.initial_action_mean=[0,0,0,-0.1,0,0]",  # initial weights, replaced by pretrained
        "logger=csv",
        "hydra.run.dir=d",
        cwd=tmp_path,
    )
    assert finetune.returncode == 0, finetune.stderr
    d = load_checkpoint(tmp_path / "d/checkpoints/last.pt")
    assert d["env_config"]["num_agents"] == 6 and d["iteration"] == 2
    # the pretrained weights' zero-shot score opens the curve, before any update
    (logged,) = (tmp_path / "d/logs").glob("*/scalars/eval_goal_fraction.csv")
    steps = [int(line.split(",")[0]) for line in logged.read_text().splitlines()]
    assert steps[0] == 0 and steps[-1] == d["env_steps"]

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
    # the energy: the heuristic's surface pushes its spheres
    assert report["scene"]["count_surface_work"]
    assert report["baselines"]["heuristic"]["surface_work_per_episode"] > 0
    with Image.open(tmp_path / "e/rollout.gif") as video:
        assert video.n_frames >= 2  # the reset frame and one per decision (GIFs merge repeats)


without_cuda = pytest.mark.skipif(torch.cuda.is_available(), reason="needs a machine without CUDA")


@pytest.mark.slow
@without_cuda
@pytest.mark.parametrize(
    ("overrides", "line", "sizes"),
    [
        (
            [],
            "no CUDA device: a CPU-sized run (model=small train.num_envs=32 train.compile=false "
            "run.eval_episodes=16 run.minutes=5 run.threads=1); "
            "set run.device=cpu to keep the configured sizes",
            (32, 32, 16),
        ),
        (
            ["train=smoke", "model=table1"],
            "no CUDA device: a CPU-sized run (run.eval_episodes=16 run.minutes=5 run.threads=1)",
            (4, 128, 16),
        ),
        # the configured network uncompiled: compiling it would take minutes of these cores
        (
            ["run.device=cpu", "train.num_envs=4", "train.minibatches=2", "train.compile=false"],
            None,
            (4, 64, 128),
        ),
    ],
    ids=["configured", "train-and-model-given", "device-cpu"],
)
def test_without_cuda_auto_sizes_a_run_for_the_cpu_but_what_the_command_line_sets(
    tmp_path, overrides, line, sizes
):
    result = run(
        "mapoca_pretrain.py",
        "env=smoke",
        "train.steps_per_iteration=8",
        "run.total_env_steps=1",
        "run.eval_every=null",
        "logger=none",
        *overrides,
        "hydra.run.dir=a",
        cwd=tmp_path,
        config_name=None,
    )
    assert result.returncode == 0, result.stderr
    if line is None:
        assert "no CUDA device" not in result.stdout
    else:
        assert line in result.stdout
    cfg = OmegaConf.load(tmp_path / "a/config.yaml")
    assert (cfg.train.num_envs, cfg.model.embed_dim, cfg.run.eval_episodes) == sizes
    assert not cfg.train.compile  # run.cpu_defaults, train=smoke, the command line
    last = load_checkpoint(tmp_path / "a/checkpoints/last.pt")
    assert last["env_steps"] == 8 * sizes[0]
    assert last["model_config"]["embed_dim"] == sizes[1]


@pytest.mark.slow
@without_cuda
def test_without_cuda_finetuning_builds_the_network_of_its_checkpoint(tmp_path):
    # a checkpoint of another model than the CPU-sized run's model=small and the configured one
    pretrained = run(
        "mapoca_pretrain.py",
        "model=table1",
        "run.total_env_steps=1",
        "hydra.run.dir=a",
        cwd=tmp_path,
    )
    assert pretrained.returncode == 0, pretrained.stderr
    finetune = [
        "mapoca_finetune.py",
        "run.pretrained=a/checkpoints/last.pt",
        "env=smoke",
        "train.steps_per_iteration=8",
        "run.total_env_steps=1",
        "run.eval_every=null",
        "logger=none",
    ]
    result = run(*finetune, "hydra.run.dir=b", cwd=tmp_path, config_name=None)
    assert result.returncode == 0, result.stderr
    assert (
        "no CUDA device: a CPU-sized run (train.num_envs=32 train.compile=false "
        "run.eval_episodes=16 run.minutes=5 run.threads=1) with the model "
        "of run.pretrained; set run.device=cpu to keep the configured sizes"
    ) in result.stdout
    saved = load_checkpoint(tmp_path / "a/checkpoints/last.pt")["model_config"]
    assert load_checkpoint(tmp_path / "b/checkpoints/last.pt")["model_config"] == saved
    assert OmegaConf.to_container(OmegaConf.load(tmp_path / "b/config.yaml").model) == saved
    # resuming it on the CPU takes the model of its checkpoint too
    more = ("run.total_env_steps=512", "run.resume=b/checkpoints/last.pt", "hydra.run.dir=c")
    resumed = run(*finetune, *more, cwd=tmp_path, config_name=None)
    assert resumed.returncode == 0, resumed.stderr
    assert load_checkpoint(tmp_path / "c/checkpoints/last.pt")["iteration"] == 2
    # a model the command line sets is built as given, and refused when it differs
    given = run(*finetune, "model=small", "hydra.run.dir=d", cwd=tmp_path, config_name=None)
    assert given.returncode != 0
    assert "holds a network of another shape" in given.stderr
    # a policy of shape actions (the recipe's) is refused on a scene of delta actions
    delta = run(
        *finetune, "env.action_mode=delta", "hydra.run.dir=f", cwd=tmp_path, config_name=None
    )
    assert delta.returncode != 0
    assert "run.pretrained was trained with env.action_mode=shape" in delta.stderr
    # with the configured sizes (as on a GPU), the checkpoint's model replaces the configured one
    configured = run(
        *finetune,
        "run.device=cpu",
        "train=smoke",
        "hydra.run.dir=e",
        cwd=tmp_path,
        config_name=None,
    )
    assert configured.returncode == 0, configured.stderr
    assert "the model of run.pretrained: it differs from the configured one in embed_dim" in (
        configured.stdout
    )
    assert load_checkpoint(tmp_path / "e/checkpoints/last.pt")["model_config"] == saved


@pytest.mark.slow
@without_cuda
@pytest.mark.parametrize(
    ("overrides", "episodes", "line"),
    [
        (
            [],
            16,
            "no CUDA device: a CPU-sized run (episodes=16 video.every=4 threads=1); set device=cpu",
        ),
        (
            ["episodes=3"],
            3,
            "no CUDA device: a CPU-sized run (video.every=4 threads=1); set device=cpu",
        ),
    ],
    ids=["configured", "episodes-given"],
)
def test_without_cuda_evaluate_scores_fewer_episodes_unless_told(
    tmp_path, overrides, episodes, line
):
    result = run(
        "evaluate.py",
        "env=smoke",
        "video.steps=0",
        *overrides,
        "hydra.run.dir=e",
        cwd=tmp_path,
        config_name=None,
    )
    assert result.returncode == 0, result.stderr
    assert line in result.stdout
    report = json.loads((tmp_path / "e/evaluation.json").read_text())
    assert report["episodes"] == episodes
    assert {scores["episodes"] for scores in report["baselines"].values()} == {episodes}


def start_pretraining(tmp_path: Path, overrides: list[str]) -> subprocess.Popen:
    """The smoke pretraining with ``overrides``, run folder ``k``, its output piped, in a process
    group of its own (which a terminal's Ctrl-C signals as a whole)."""
    command = [sys.executable, str(RECIPES / "mapoca_pretrain.py"), "--config-name", "smoke"]
    return subprocess.Popen(
        [*command, *overrides, "hydra.run.dir=k"],
        cwd=tmp_path,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
    )


def ctrl_c(process: subprocess.Popen) -> tuple[str, str, float]:
    """Ctrl-C to ``process``'s group; its output and the seconds from the signal to its exit."""
    os.killpg(process.pid, signal.SIGINT)
    signalled = time.monotonic()
    stdout, stderr = process.communicate(timeout=600)
    return stdout, stderr, time.monotonic() - signalled


@pytest.mark.slow
def test_a_terminated_run_checkpoints_a_whole_iteration(tmp_path):
    # SIGTERM lands mid-iteration more often than not; the run finishes that iteration first,
    # so its checkpoint equals that of a run told to stop there
    killed = start_pretraining(tmp_path, ["run.total_env_steps=1000000", "run.checkpoint_every=1"])
    deadline = time.monotonic() + 300
    while not (tmp_path / "k/checkpoints/last.pt").exists() and time.monotonic() < deadline:
        time.sleep(0.1)
    time.sleep(1.0)
    killed.send_signal(signal.SIGTERM)
    stdout, stderr = killed.communicate(timeout=300)
    assert killed.returncode == 0, stderr
    assert "SIGTERM: stopping after this iteration" in stdout
    k = load_checkpoint(tmp_path / "k/checkpoints/last.pt")
    straight = run(
        "mapoca_pretrain.py",
        f"run.total_env_steps={k['env_steps']}",
        "hydra.run.dir=s",
        cwd=tmp_path,
    )
    assert straight.returncode == 0, straight.stderr
    s = load_checkpoint(tmp_path / "s/checkpoints/last.pt")
    assert s["iteration"] == k["iteration"]
    for name, value in s["networks"].items():
        torch.testing.assert_close(k["networks"][name], value, atol=0, rtol=0)
    torch.testing.assert_close(k["simulator"], s["simulator"], atol=0, rtol=0)


def wait_for(condition, what: str, timeout: float = 300.0) -> None:
    deadline = time.monotonic() + timeout
    while not condition():
        assert time.monotonic() < deadline, f"no {what} within {timeout:.0f} s"
        time.sleep(0.05)


@pytest.mark.slow
def test_ctrl_c_checkpoints_exits_in_seconds_and_prints_the_command_that_resumes(tmp_path):
    # episodes of 4,096 decisions: a final evaluation would take minutes, the stop skips it
    overrides = [
        "run.total_env_steps=1000000",
        "run.checkpoint_every=1",
        "run.eval_every=1000",
        "env.max_episode_steps=4096",
    ]
    interrupted = start_pretraining(tmp_path, overrides)
    last = tmp_path / "k/checkpoints/last.pt"
    try:
        wait_for(last.exists, "first checkpoint")
        first = last.stat().st_mtime
        wait_for(lambda: last.stat().st_mtime != first, "second checkpoint")
        iteration_s = last.stat().st_mtime - first  # on a loaded machine, iterations slow down
        stdout, stderr, exit_s = ctrl_c(interrupted)
    finally:
        interrupted.kill()
    assert interrupted.returncode == 0, stderr
    # the iteration under way ends, its checkpoint is written, then the run exits
    assert exit_s < 20 + 2 * iteration_s, f"exited {exit_s:.0f} s after Ctrl-C"
    assert "SIGINT: stopping after this iteration" in stdout
    assert "final evaluation" not in stderr and "evaluation at" not in stdout
    stopped = load_checkpoint(last)
    assert stopped["iteration"] >= 2
    (line,) = [line for line in stdout.splitlines() if line.startswith("resume with: ")]
    resume = shlex.split(line.removeprefix("resume with: "))
    script = str(RECIPES / "mapoca_pretrain.py")
    assert resume == [
        "python",
        script,
        "--config-name",
        "smoke",
        *overrides,
        f"run.resume={last.relative_to(tmp_path)}",
    ]
    # the printed command resumes it, in its run's folder (one more iteration here)
    more = [f"run.total_env_steps={stopped['env_steps'] + 1}", "run.eval_every=null"]
    resumed = subprocess.run(
        [sys.executable, *resume[1:], *more], cwd=tmp_path, capture_output=True, text=True
    )
    assert resumed.returncode == 0, resumed.stderr
    assert load_checkpoint(last)["iteration"] == stopped["iteration"] + 1
    assert not (tmp_path / "outputs").exists()
    log = (tmp_path / "k/mapoca_pretrain.log").read_text()
    assert "SIGINT: stopping after this iteration" in log and line in log  # the first run's too


@pytest.mark.slow
@pytest.mark.parametrize("checkpointed", [True, False])
def test_a_second_ctrl_c_quits_at_once_saying_what_it_keeps(tmp_path, checkpointed):
    # iterations of 8,192 decisions, seconds each: the second signal lands in the iteration
    # that the first one lets finish
    overrides = [
        "run.total_env_steps=1000000",
        "train.num_envs=128",
        "train.steps_per_iteration=64",
        f"run.checkpoint_every={1 if checkpointed else 1000}",
    ]
    interrupted = start_pretraining(tmp_path, overrides)
    last, log = tmp_path / "k/checkpoints/last.pt", tmp_path / "k/mapoca_pretrain.log"
    try:
        if checkpointed:
            wait_for(last.exists, "first checkpoint")
        else:
            wait_for(lambda: log.exists() and "env-steps" in log.read_text(), "run line")
        # inside the next iteration: past the start of the run's handler, or past the end of
        # the checkpointed iteration (a signal before its end would stop the run right there)
        time.sleep(0.5)
        os.killpg(interrupted.pid, signal.SIGINT)
        wait_for(lambda: "SIGINT: stopping" in log.read_text(), "answer to the first Ctrl-C")
        stdout, stderr, exit_s = ctrl_c(interrupted)
    finally:
        interrupted.kill()
    assert interrupted.returncode == 130, stderr
    assert exit_s < 30, f"exited {exit_s:.0f} s after the second Ctrl-C"  # a hang guard
    (said,) = [line for line in stdout.splitlines() if line.startswith("interrupted during ")]
    resumes = [line for line in stdout.splitlines() if line.startswith("resume with: ")]
    if not checkpointed:
        assert said == "interrupted during the iteration, before a checkpoint was written"
        assert not last.exists() and resumes == []
        return
    assert said.endswith(f"; {last.relative_to(tmp_path)} is the last checkpoint")
    assert load_checkpoint(last)["iteration"] >= 1  # a whole one: written before, never half
    (line,) = resumes
    assert shlex.split(line.removeprefix("resume with: "))[2:] == [
        "--config-name",
        "smoke",
        *overrides,
        f"run.resume={last.relative_to(tmp_path)}",
    ]


@pytest.mark.slow
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
    best = load_checkpoint(tmp_path / "a/checkpoints/best.pt")
    assert len(rewards) == 4
    assert best["mean_reward_per_decision"] == pytest.approx(means[best_index], rel=1e-6)
    assert best["env_steps"] == steps[best_index + 1]
    assert best["iteration"] == best_index + 2
    last = load_checkpoint(tmp_path / "a/checkpoints/last.pt")
    assert last["best"]["reward"] == best["mean_reward_per_decision"]
    assert last["best"]["recent"] == pytest.approx(rewards[-2:], rel=1e-6)
    # a snapshot every 2 iterations: the weights and counters of that iteration
    snapshots = sorted(path.name for path in (tmp_path / "a/checkpoints").glob("iteration_*.pt"))
    assert snapshots == ["iteration_000002.pt", "iteration_000004.pt"]
    second = load_checkpoint(tmp_path / "a/checkpoints/iteration_000002.pt")
    assert (second["iteration"], second["env_steps"]) == (2, steps[1])
    fourth = load_checkpoint(tmp_path / "a/checkpoints/iteration_000004.pt")
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
    # on a scene of the command line's, the policy's actions must mean what they meant
    other = ("scene_from_checkpoint=false", "env=smoke", "env.action_mode=delta")
    refused = run(
        "evaluate.py",
        "checkpoint=a/checkpoints/best.pt",
        *other,
        "hydra.run.dir=f",
        cwd=tmp_path,
        config_name=None,
    )
    assert refused.returncode != 0
    assert "checkpoint was trained with env.action_mode=shape" in refused.stderr
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


@pytest.mark.slow
@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        (["train.minibatches=99"], "minibatches"),
        (["run.best_window=-1"], "run.best_window"),
        (["run.snapshot_every=0"], "run.snapshot_every"),
        (["+env.grid_sise=10"], "env.grid_sise is not a setting"),
        (["train.nope=1"], "Could not override 'train.nope'"),
        (["run.resume=missing.pt"], "no checkpoint at"),
        (["logger.kind=paper"], "logger.kind"),
    ],
)
def test_bad_configuration_fails_at_start_up(tmp_path, overrides, message):
    result = run("mapoca_pretrain.py", *overrides, "hydra.run.dir=x", cwd=tmp_path)
    assert result.returncode != 0
    assert message in result.stderr


@pytest.mark.slow
def test_evaluate_rejects_a_respawn_that_is_not_a_boolean(tmp_path):
    result = run(
        "evaluate.py", "respawn=sometimes", "hydra.run.dir=x", cwd=tmp_path, config_name=None
    )
    assert result.returncode != 0
    assert "respawn must be true or false, got 'sometimes'" in result.stderr


def configs_of(cfg) -> dict:
    """The configs a run of ``cfg`` compares with a checkpoint's."""
    settings = RecipeConfig.of(cfg)
    return {
        "env_config": dataclasses.asdict(settings.env),
        "model_config": dataclasses.asdict(settings.model),
        "train_config": dataclasses.asdict(settings.train),
        "curriculum_config": dataclasses.asdict(settings.curriculum),
        "algo": settings.train.algo,
    }


def test_resume_ignores_settings_that_only_set_the_initial_weights():
    configs = configs_of(compose_config("smoke"))
    change = {"initial_action_mean": [0.0, 0.0, 0.0, -0.1, 0.0, 0.0]}
    saved = {**configs, "model_config": {**configs["model_config"], **change}}
    check_resumable(saved, configs, path="last.pt")
    wider = {**configs, "model_config": {**configs["model_config"], "embed_dim": 64}}
    with pytest.raises(ValueError, match="add model.embed_dim=64 to continue"):
        check_resumable(wider, configs, path="last.pt")


def test_resume_reads_a_setting_saved_under_its_earlier_name():
    configs = configs_of(compose_config("smoke"))
    train = configs["train_config"]
    flat = {**{k: v for k, v in train.items() if k != "loss"}, **train["loss"]}
    flat["value_clip_start"] = flat.pop("clip_value_start")  # before the rename
    saved = upgrade({"networks": {}, **configs, "algo": "mapoca", "train_config": flat})
    check_resumable(saved, configs, path="last.pt")
    saved["train_config"]["loss"]["clip_value_start"] = 0.5
    with pytest.raises(ValueError, match="add loss.clip_value_start=0.5 to continue"):
        check_resumable(saved, configs, path="last.pt")


def test_resume_with_another_algorithm_names_it():
    configs = configs_of(compose_config("smoke"))
    saved = configs_of(compose_config("smoke", "algo=mappo"))
    with pytest.raises(ValueError, match="add algo=mappo to continue"):
        check_resumable(saved, configs, path="last.pt")


def test_resume_with_another_curriculum_names_it():
    configs = configs_of(compose_config("smoke"))
    saved = configs_of(compose_config("smoke", "curriculum=auto", "curriculum.stages=4"))
    with pytest.raises(ValueError, match="add curriculum.kind=auto curriculum.stages=4 to"):
        check_resumable(saved, configs, path="last.pt")
    earlier = {key: value for key, value in configs.items() if key != "curriculum_config"}
    check_resumable(earlier, configs, path="last.pt")  # saved before the curriculum: none
    other_scoring = configs_of(compose_config("smoke", "curriculum.retention_every=7"))
    check_resumable(other_scoring, configs, path="last.pt")  # what is scored may change


@pytest.mark.slow
def test_resume_names_the_settings_that_differ_from_the_checkpoints(tmp_path):
    first = run("mapoca_pretrain.py", "train.minibatches=1", "hydra.run.dir=b", cwd=tmp_path)
    assert first.returncode == 0, first.stderr
    result = run(
        "mapoca_pretrain.py",
        "run.resume=b/checkpoints/last.pt",
        "model.embed_dim=64",
        "loss.gamma=0.9",
        "train.compile=true",  # how the networks execute may change
        "hydra.run.dir=y",
        cwd=tmp_path,
    )
    assert result.returncode != 0
    assert "add model.embed_dim=32 train.minibatches=1 loss.gamma=0.95 to continue" in (
        result.stderr
    )


def test_the_smoke_config_takes_every_train_setting():
    cfg = compose_config("smoke", "train.lr_trunk_policy=0.001", "train.compile=true")
    assert cfg.train.lr_trunk_policy == 0.001 and cfg.train.compile
    assert set(cfg.train) == set(compose_config("mapoca_pretrain").train)


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        ("run.checkpoint_every=0", "run.checkpoint_every must be an integer >= 1, got 0"),
        ("run.seed=abc", r"run.seed must be an integer in \[0, 2\*\*64\), got 'abc'"),
        ("run.total_env_steps=-64", "run.total_env_steps must be an integer >= 1, got -64"),
        ("run.total_env_steps=1e3", "run.total_env_steps must be an integer >= 1, got 1000.0"),
        ("run.minutes=-1", r"run.minutes must be a finite number > 0 or null \(no time limit\)"),
        ("run.minutes=nan", "run.minutes must be a finite number > 0 .*, got nan"),
        ("run.eval_every=0", "run.eval_every must be an integer >= 1 or null"),
        ("run.name=''", "run.name must be a name of 1 to 100 letters, digits"),
        ("run.device=tpu", "run.device must be auto, cpu, cuda or cuda:<index>, got 'tpu'"),
        ("run.cpu_defaults=small", r"run.cpu_defaults must be a list of .*, got .small.$"),
        ("logger=wandb logger.mode=loud", "logger.mode must be one of offline, online, got 'loud'"),
        ("train.lr_trunk_policy=-1", "train.lr_trunk_policy must be a finite number > 0"),
        ("train.lr_value_baseline=inf", r"train.lr_value_baseline must be .*, got inf"),
        ("train.max_grad_norm_start=-1", "train.max_grad_norm_start must be"),
        ("train.schedule_iterations=0", "train.schedule_iterations must be an integer >= 1"),
        ("train.lr_end_factor=-0.1", "train.lr_end_factor must be"),
        ("loss.entropy_coeff_start=nan", "loss.entropy_coeff_start must be .*, got nan"),
        ("loss.clip_epsilon_start=1.5", r"loss.clip_epsilon_start must be .* \(0, 1\)"),
        ("loss.value_coeff=-1", "loss.value_coeff must be a finite number >= 0"),
        ("env.num_agents=0", "env.num_agents must be an integer >= 1"),
    ],
)
def test_every_kind_of_bad_setting_fails_before_an_environment_is_built(
    monkeypatch, tmp_path, overrides, message
):
    def no_environment(*args, **kwargs):
        raise AssertionError("an environment was built before the settings were checked")

    monkeypatch.setattr(pretrain, "make_training_env", no_environment)
    with pytest.raises(ValueError, match=f"^{message}"):
        pretrain.train(compose_config("smoke", *overrides.split()), run_dir=tmp_path)


@pytest.mark.skipif(torch.cuda.is_available(), reason="needs a machine without CUDA")
def test_cuda_without_cuda_is_refused_at_start_up(tmp_path):
    with pytest.raises(ValueError, match="run.device=cuda, but this machine has 0 CUDA device"):
        pretrain.train(compose_config("smoke", "run.device=cuda"), run_dir=tmp_path)


@pytest.mark.parametrize(
    ("override", "message"),
    [
        ("episodes=0", "episodes must be an integer >= 1, got 0"),
        ("seed=-1", r"seed must be an integer in \[0, 2\*\*64\), got -1"),
        ("video.format=avi", "video.format must be one of mp4, gif, got 'avi'"),
        ("video.fps=0", "video.fps must be a finite number > 0, got 0"),
        ("baselines=maybe", "baselines must be true or false, got 'maybe'"),
        ("checkpoint=7", r"checkpoint must be a non-empty path or null \(the baselines alone\)"),
        ("respawn=sometimes", "respawn must be true or false"),
        ("+episode=3", "episode is not a setting"),
        ("cpu_defaults=[episodes]", r"cpu_defaults must be a list of overrides \(key=value\)"),
    ],
)
def test_evaluation_settings_are_checked(override, message):
    EvaluateConfig.of(compose_config("evaluate"))
    with pytest.raises(ValueError, match=f"^{message}"):
        EvaluateConfig.of(compose_config("evaluate", override))


def test_the_resume_hint_pastes_into_a_shell_as_it_is():
    cfg = compose_config("smoke")
    saved = configs_of(cfg)
    saved["env_config"].update(column_shape="box", wrap_edges=False)
    saved["model_config"].update(cnn_channels=[8, 16, 16])
    saved["train_config"].update(lr_schedule="adaptive")
    saved["train_config"]["loss"].update(gamma=0.9)
    with pytest.raises(ValueError, match="add (.*) to continue it") as refused:
        check_resumable(saved, configs_of(cfg), path="last.pt")
    hint = str(refused.value).split("; add ")[1].split(" to continue it")[0]
    assert "'model.cnn_channels=[8,16,16]'" in hint.split()
    resumed = compose_config("smoke", *shlex.split(hint))
    check_resumable(saved, configs_of(resumed), path="last.pt")  # nothing differs


@pytest.mark.slow
def test_a_run_that_turns_non_finite_stops_and_keeps_the_last_good_checkpoint(tmp_path):
    result = run(
        "mapoca_pretrain.py",
        "train.lr_end_factor=1e10",  # the learning rates jump to 3e6 after the first update
        "train.schedule_iterations=1",
        "run.total_env_steps=96",
        "run.eval_every=null",
        "hydra.run.dir=a",
        cwd=tmp_path,
    )
    assert result.returncode == 1
    assert "iteration 2 made loss_objective = nan" in result.stderr
    assert "stopped without saving that iteration" in result.stderr
    last = load_checkpoint(tmp_path / "a/checkpoints/last.pt")
    assert last["iteration"] == 1
    assert all(value.isfinite().all() for value in last["networks"].values())


@pytest.mark.slow
def test_evaluate_refuses_a_checkpoint_that_would_run_code(tmp_path):
    class CreatesAFile:
        def __reduce__(self):
            return (open, (str(tmp_path / "created_by_loading"), "w"))

    torch.save({"networks": CreatesAFile()}, tmp_path / "shared.pt")
    result = run("evaluate.py", "checkpoint=shared.pt", cwd=tmp_path, config_name=None)
    assert result.returncode != 0
    assert "refused to load shared.pt: loading it would call" in result.stderr
    assert not (tmp_path / "created_by_loading").exists()


@pytest.mark.slow
@pytest.mark.parametrize("algo", ["mappo", "ippo"])
def test_every_algorithm_trains_resumes_and_finetunes_from_the_recipes(tmp_path, algo):
    steps = ("run.total_env_steps=64", "run.eval_every=null")
    first = run("mapoca_pretrain.py", f"algo={algo}", *steps, "hydra.run.dir=a", cwd=tmp_path)
    assert first.returncode == 0, first.stderr[-2000:]
    last = tmp_path / "a/checkpoints/last.pt"
    assert load_checkpoint(last)["algo"] == algo
    more = ("run.total_env_steps=128", "run.eval_every=null", f"run.resume={last}")
    resumed = run("mapoca_pretrain.py", f"algo={algo}", *more, "hydra.run.dir=b", cwd=tmp_path)
    assert resumed.returncode == 0, resumed.stderr[-2000:]
    assert load_checkpoint(tmp_path / "b/checkpoints/last.pt")["env_steps"] == 128
    other = run("mapoca_pretrain.py", "algo=mapoca", *more, "hydra.run.dir=c", cwd=tmp_path)
    assert other.returncode != 0 and f"algo={algo}" in other.stderr
