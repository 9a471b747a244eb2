"""Path-like names: a setting that becomes a file's name (``run.name``, ``logger.project``) is a
name, never a path, refused at start-up by its key, with a length limit."""

import pytest
from test_hostile_settings import refusal, refused_in_subprocess
from test_settings import composed

from terrashift_rl.fields import build
from terrashift_rl.training.loggers import make_logger
from terrashift_rl.training.settings import LoggerConfig, RecipeConfig, RunConfig

NAMES = [(RunConfig, "run", "name"), (LoggerConfig, "logger", "project")]
"""The settings that name a file or folder."""


@pytest.mark.parametrize(
    "name",
    [
        "../../../../x",
        "/tmp/x",
        "a/b",
        "a\\b",
        "..",
        ".",
        ".hidden",
        "",
        "x" * 101,
        "x" * 5000,
        "nul\x00byte",
        "new\nline",
        "with space",
        "naïve",
        "$HOME",
        "${oc.env:HOME}",
        "~",
    ],
)
@pytest.mark.parametrize(("settings", "group", "key"), NAMES)
def test_a_name_that_is_not_a_plain_name_is_refused_by_its_key(settings, group, key, name):
    with pytest.raises(ValueError) as error:
        build(settings, {key: name}, group)
    message = str(error.value)
    assert message.startswith(f"{group}.{key} must be a name of 1 to 100 letters")
    assert len(message.splitlines()) == 1 and len(message) < 300


def test_a_path_given_as_run_name_on_the_command_line_is_refused():
    assert refusal("run.name=../../x").startswith("run.name must be a name")


@pytest.mark.parametrize("name", ["mapoca_pretrain", "run-2.b", "lr3e-4+kl", "x" * 100])
def test_a_plain_name_is_taken(name):
    assert RecipeConfig.of(composed(f"run.name={name}")).run.name == name


def test_a_csv_logger_writes_below_the_run_folder_alone(tmp_path):
    run_dir = tmp_path / "run"
    logger = make_logger(LoggerConfig(kind="csv"), "run-1.b", run_dir, None)
    logger.log_scalar("reward", 1.0, step=1)
    written = [path for path in tmp_path.rglob("*") if path.is_file()]
    assert written and all(path.is_relative_to(run_dir / "logs") for path in written)


@pytest.mark.slow
def test_a_recipe_refuses_a_run_name_that_climbs_out_of_its_folder(tmp_path):
    name = "../../../../hostile_name"
    stderr = refused_in_subprocess(
        "mapoca_pretrain.py", "logger=csv", f"run.name={name}", cwd=tmp_path
    )
    assert "run.name must be a name of 1 to 100 letters" in stderr
    assert not (tmp_path / "run" / "logs" / name).resolve().exists()
