"""Hostile settings: every setting of the room typed and ranged, unknown keys refused in every
group and at the top level, and values that make the reward or the loss non-finite by
construction refused at start-up, each by its key in one line. A recipe run in a subprocess ends a
refusal with that message alone (at most 20 lines) and writes nothing outside its run folder."""

import math
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from test_settings import ROOT, composed
from test_trainer import make_trainer

from terrashift_rl.envs import TerraShiftEnv
from terrashift_rl.sim import TerraShiftConfig
from terrashift_rl.training.settings import (
    EvaluateConfig,
    RecipeConfig,
    check_reward_range,
    reward_bound,
)

MAX_REFUSAL_LINES = 20


def refused_in_subprocess(
    script: str, *overrides: str, cwd: Path, env: dict | None = None, config: str = "smoke"
) -> str:
    """Runs ``recipes/<script>`` with the ``config`` and ``overrides`` writing into
    ``cwd/run``; asserts that it is refused (exit status 1) in at most
    ``MAX_REFUSAL_LINES`` lines of stderr with no traceback, and that it wrote nothing in
    ``cwd`` but its run folder. Returns stderr."""
    there = {path.name for path in cwd.iterdir()}
    result = subprocess.run(
        [sys.executable, str(ROOT / "recipes" / script), "--config-name", config, *overrides]
        + ["hydra.run.dir=run"],
        cwd=cwd,
        capture_output=True,
        text=True,
        timeout=600,
        env=env,
    )
    assert result.returncode == 1, result.stderr
    assert len(result.stderr.splitlines()) <= MAX_REFUSAL_LINES, result.stderr
    assert "Traceback" not in result.stderr
    assert {path.name for path in cwd.iterdir()} <= {*there, "run"}
    return result.stderr


def refusal(*overrides: str) -> str:
    with pytest.raises(ValueError) as error:
        RecipeConfig.of(composed(*overrides))
    message = str(error.value)
    assert len(message.splitlines()) == 1, message
    assert len(message) <= 80 * MAX_REFUSAL_LINES  # at most 20 lines of a terminal
    return message


@pytest.mark.parametrize(
    ("override", "start"),
    [
        ("+foo=1", "foo is not a setting; the config groups are"),
        ("+run.foo=1", "run.foo is not a setting"),
        ("+env.foo=1", "env.foo is not a setting"),
        ("+model.foo=1", "model.foo is not a setting"),
        ("+train.foo=1", "train.foo is not a setting"),
        ("+loss.foo=1", "loss.foo is not a setting of algo=mapoca"),
        ("+logger.foo=1", "logger.foo is not a setting"),
        ("run.seed=18446744073709551616", "run.seed must be an integer in [0, 2**64)"),
        ("run.seed=-1", "run.seed must be an integer in [0, 2**64)"),
        ("run.resume=''", "run.resume must be a non-empty path or null"),
        ("run.pretrained=''", "run.pretrained must be a non-empty path or null"),
        ("model.embed_dim=0", "model.embed_dim must be an integer >= 1, got 0"),
        ("model.dropout=1.5", "model.dropout must be a finite number in [0, 1), got 1.5"),
        ("model.cnn_channels=[0,8,8]", "model.cnn_channels must be a list of 1 to 8 integers"),
        ("model.trunk_layers=1000000", "model.trunk_layers must be an integer in [1, 64]"),
        ("model.embed_dim=10000000", "model: the networks would hold 6e+15 parameters"),
        ("model.ffn_dim=1000000000", "model: the networks would hold"),
        ("train.cuda_graphs=2", "train.cuda_graphs must be true or false, got 2"),
        ("train.num_envs=1.5", "train.num_envs must be an integer >= 1, got 1.5"),
        ("env.wrap_edges=2", "env.wrap_edges must be true or false, got 2"),
        ("env.reward_normalizer=1e-300", "env.reward_normalizer (1e-300) is 0 in float32"),
        ("env.distance_scale=1e308", "env.distance_scale (1e+308) with env.reward_normalizer"),
        ("env.goal_reward=1e39", "env.goal_reward (1e+39) with env.reward_normalizer"),
        ("loss.value_coeff=1e308", "loss.value_coeff (1e+308) times the largest squared"),
        ("loss.baseline_coeff=1e35", "loss.baseline_coeff (1e+35) times the largest squared"),
        ("loss.entropy_coeff_start=1e308", "loss.entropy_coeff_start (1e+308) times"),
    ],
)
def test_a_hostile_setting_is_refused_by_its_key(override, start):
    assert refusal(override).startswith(start)


def test_a_long_value_is_shown_cut_to_one_short_line():
    message = refusal("run.name=" + "x" * 5000)
    assert message.startswith("run.name must be a name") and "(5002 characters)" in message


def test_the_paper_scenes_rewards_and_losses_are_far_from_float32s_limits():
    for config in ("smoke", "mapoca_pretrain", "mapoca_paper", "mapoca_finetune"):
        RecipeConfig.of(composed(config=config))  # every product check passes
    bound = sum(reward_bound(TerraShiftConfig()).values())
    assert 1 < bound < 1e4


def test_the_reward_bound_holds_on_a_rollout():
    scene = TerraShiftConfig(grid_size=8, num_agents=2, num_objects=2, num_goals=2)
    env = TerraShiftEnv(scene, num_envs=4, seed=0)
    reward = env.rollout(30)["next", "agents", "reward"]
    assert reward.abs().max() <= sum(reward_bound(scene).values())


def test_the_evaluation_recipe_refuses_a_scene_whose_reward_is_infinite():
    with pytest.raises(ValueError, match=r"^env.reward_normalizer \(1e-300\) is 0 in float32"):
        EvaluateConfig.of(composed("env.reward_normalizer=1e-300", config="evaluate"))
    with pytest.raises(ValueError, match=r"^scene.distance_scale"):
        check_reward_range(TerraShiftConfig(distance_scale=1e38, distance_clip=1e3), "scene")


def test_a_non_finite_loss_names_the_raised_coefficient_first():
    trainer = make_trainer(value_coeff=1.0e38, baseline_coeff=1.0e38)
    with pytest.raises(FloatingPointError) as error:
        for _ in range(3):
            trainer.train_iteration()
    message = str(error.value)
    assert "lower loss." in message and "raised above the default" in message, message
    assert math.isfinite(make_trainer().train_iteration()["loss_total"])


@pytest.mark.skipif(torch.cuda.is_available(), reason="needs a machine without CUDA")
def test_an_environment_on_cuda_without_cuda_says_so():
    with pytest.raises(ValueError, match="^device 'cuda' requested but CUDA is not available"):
        TerraShiftEnv(device="cuda")


@pytest.mark.slow
def test_a_recipe_refuses_a_loss_that_would_be_infinite_in_one_message(tmp_path):
    stderr = refused_in_subprocess("mapoca_pretrain.py", "loss.value_coeff=1e308", cwd=tmp_path)
    assert "loss.value_coeff (1e+308) times the largest squared return" in stderr
    assert not (tmp_path / "run" / "checkpoints" / "last.pt").exists()
