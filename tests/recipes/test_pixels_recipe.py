"""The pixels recipe: trains from the camera without the object sequence (which the critics
alone read), in one scene or through a curriculum; a scene that lacks what the networks read,
or hands out what they do not, a teacher without the objects (observed or privileged), or
privileged objects where they are observed or no critic reads them, is refused at start-up."""

import importlib.util
import subprocess
import sys
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir

from terrashift_rl.training import load_checkpoint

RECIPES = Path(__file__).resolve().parents[2] / "recipes"
spec = importlib.util.spec_from_file_location("mapoca_pretrain", RECIPES / "mapoca_pretrain.py")
pretrain = importlib.util.module_from_spec(spec)
spec.loader.exec_module(pretrain)  # registers the config schemas

TINY = ["env=smoke", "model=small", "train=smoke", "logger=none", "run.device=cpu"]
"""The pixels recipe at the smoke config's sizes."""


def train_pixels(tmp_path: Path, *overrides: str) -> tuple[str, dict]:
    """Runs the pixels recipe at the smoke sizes with a 16 x 16 camera for 64 env-steps; its
    output and its last checkpoint."""
    result = subprocess.run(
        [
            sys.executable,
            str(RECIPES / "mapoca_pretrain.py"),
            "--config-name",
            "mapoca_pixels",
            *TINY,
            "env.camera_resolution=16",
            "run.total_env_steps=64",
            *overrides,
            "hydra.run.dir=a",
        ],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert result.returncode == 0, result.stderr
    return result.stdout, load_checkpoint(tmp_path / "a/checkpoints/last.pt")


@pytest.mark.slow
def test_the_pixels_recipe_trains_from_the_camera_alone(tmp_path):
    _, checkpoint = train_pixels(tmp_path, "run.eval_every=1", "run.eval_episodes=2")
    assert checkpoint["env_config"]["camera_resolution"] == 16
    assert checkpoint["env_config"]["observe_objects"] is False
    assert checkpoint["model_config"]["camera_channels"] == 1
    assert checkpoint["model_config"]["object_tokens"] is False
    # the critics alone read the objects: only their heads hold an object encoder
    assert checkpoint["env_config"]["privileged_objects"] is True
    assert checkpoint["model_config"]["critic_objects"] is True
    readers = {name.split(".")[0] for name in checkpoint["networks"] if "object_encoder" in name}
    assert readers == {"value_head", "baseline_head"}


def test_the_pixels_recipe_is_taught_by_the_heuristic():
    with initialize_config_dir(config_dir=str(RECIPES / "configs"), version_base=None):
        taught = compose(config_name="mapoca_pixels")
        untaught = compose(config_name="mapoca_pixels", overrides=["loss=default"])
    assert taught.loss.teacher_coeff == 10.0 and taught.loss.teacher_coeff_end == 1.0
    assert untaught.loss.teacher_coeff == 0.0


@pytest.mark.slow
def test_the_pixels_recipe_trains_through_a_curriculum(tmp_path):
    output, checkpoint = train_pixels(
        tmp_path,
        "loss=default",  # a curriculum trains without the teacher
        "curriculum=auto",
        "curriculum.start_grid_size=6",
        "curriculum.start_num_agents=2",
        "curriculum.start_num_objects=1",
        "curriculum.stages=2",
        "curriculum.threshold=0",  # advance at the first evaluation
        "curriculum.eval_every=1",
    )
    assert "stage 2/2: 8x8 columns, 4 agents, 2 spheres from 32 env-steps" in output
    assert checkpoint["curriculum"]["stage"] == 1
    assert checkpoint["env_config"]["camera_resolution"] == 16


@pytest.mark.parametrize(
    ("config", "overrides", "message"),
    [
        ("smoke", ["env.camera_resolution=16"], "model.camera_channels=0 but env.camera_resol"),
        ("mapoca_pixels", [*TINY, "env.camera_resolution=0"], "model.camera_channels=1 but env"),
        (
            "mapoca_pixels",
            [*TINY, "model.object_tokens=true", "model.critic_objects=false"],
            "model.object_tokens=true reads",
        ),
        ("mapoca_pixels", [*TINY, "model.object_tokens=true"], "model.critic_objects=true gives"),
        (
            "mapoca_pixels",
            [
                *TINY,
                "loss.teacher_coeff=0.1",
                "env.privileged_objects=false",
                "model.critic_objects=false",
            ],
            "loss.teacher_coeff=0.1: the teach",
        ),
        ("mapoca_pixels", [*TINY, "env.observe_objects=true"], "privileged_objects=true hands"),
        ("mapoca_pixels", [*TINY, "env.privileged_objects=false"], "model.critic_objects=true but"),
        ("mapoca_pixels", [*TINY, "model.critic_objects=false"], "model.critic_objects=false but"),
        (
            "mapoca_pixels",
            [*TINY, "algo=ippo", "loss=default"],
            "algo=ippo's value reads each agent's own",
        ),
    ],
)
def test_what_the_networks_read_must_be_observed(tmp_path, config, overrides, message):
    with initialize_config_dir(config_dir=str(RECIPES / "configs"), version_base=None):
        cfg = compose(config_name=config, overrides=overrides)
    with pytest.raises(ValueError, match=message):
        pretrain.train(cfg, run_dir=tmp_path)
