"""The settings room: every setting typed once, refused by name with its value and range; each
algorithm's loss settings its own; no import circle in the package."""

import ast
import dataclasses
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir
from test_trainer import train_config

from terrashift_rl.fields import build, check_value
from terrashift_rl.training import ALGORITHMS, MAPOCAConfig, MAPPOConfig, TrainConfig
from terrashift_rl.training.settings import (
    OVERRIDES,
    EvaluateConfig,
    RecipeConfig,
    RunConfig,
    loss_config,
    register_config_schemas,
)

ROOT = Path(__file__).resolve().parents[2]
PACKAGE = ROOT / "terrashift_rl"
LOSS_FIELDS = {field.name for field in dataclasses.fields(MAPOCAConfig)}


def key(field: str) -> str:
    return f"{'loss' if field in LOSS_FIELDS else 'train'}.{field}"


def composed(*overrides: str, config: str = "smoke"):
    register_config_schemas()
    with initialize_config_dir(config_dir=str(ROOT / "recipes" / "configs"), version_base=None):
        return compose(config_name=config, overrides=list(overrides))


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("teacher_coeff", -1.0),
        ("teacher_coeff", float("nan")),
        ("teacher_coeff_end", -1.0),
        ("teacher_coeff_end", 1.0),  # with no teacher (teacher_coeff 0)
        ("teacher_iterations", 0),
    ],
)
def test_bad_teacher_settings_are_refused(field, value):
    train_config()
    with pytest.raises(ValueError, match=f"^loss.{field}"):
        train_config(**{field: value})


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("lr_schedule", "cosine"),
        ("desired_kl", 0.0),
        ("desired_kl", float("nan")),
        ("lr_trunk_policy", -1e-4),
        ("lr_max", float("inf")),
        ("lr_min", 1.0),  # above lr_trunk_policy, with the adaptive schedule
        ("critic_warmup_iterations", -1),
    ],
)
def test_bad_learning_rate_settings_are_refused(field, value):
    with pytest.raises(ValueError, match=f"train.{field}"):
        train_config(**{"lr_schedule": "adaptive", field: value})


@pytest.mark.parametrize(
    "field",
    [f.name for f in dataclasses.fields(TrainConfig) if f.name != "loss"] + sorted(LOSS_FIELDS),
)
def test_every_setting_of_the_wrong_type_is_refused_by_name(field):
    with pytest.raises(ValueError, match=rf"^{key(field)} must be .*got 'junk'$"):
        train_config(**{field: "junk"})


@pytest.mark.parametrize(
    ("field", "value", "allowed"),
    [
        # signs
        ("lr_value_baseline", -1e-4, "> 0"),
        ("lr_end_factor", -0.1, "> 0"),
        ("max_grad_norm_start", -5.0, "> 0"),
        ("value_coeff", -1.0, ">= 0"),
        ("baseline_coeff", -0.5, ">= 0"),
        ("weight_decay", -0.01, ">= 0"),
        ("entropy_coeff_end", -0.001, ">= 0"),
        # zero
        ("schedule_iterations", 0, "an integer >= 1"),
        ("max_grad_norm_end", 0.0, "> 0"),
        ("clip_value_start", 0.0, "> 0"),
        ("clip_epsilon_end", 0.0, r"in \(0, 1\)"),
        ("gamma", 0.0, r"in \(0, 1\]"),
        # NaN and infinity
        ("entropy_coeff_start", float("nan"), ">= 0"),
        ("lr_trunk_policy", float("nan"), "> 0"),
        ("clip_value_end", float("inf"), "> 0"),
        ("teacher_coeff", float("inf"), ">= 0"),
        ("lmbda", float("nan"), r"in \[0, 1\]"),
        # above a range
        ("clip_epsilon_start", 1.0, r"in \(0, 1\)"),
        ("value_norm_decay", 1.0, r"in \[0, 1\)"),
        # types: booleans are booleans, integers no booleans
        ("epochs", 2.0, "an integer >= 1"),
        ("num_envs", True, "an integer >= 1"),
        ("compile", 1, "true or false"),
        ("cuda_graphs", 2, "true or false"),
        ("normalize_value", "false", "true or false"),
    ],
)
def test_a_setting_outside_its_range_is_refused_with_the_range(field, value, allowed):
    message = rf"^{key(field)} must be .*{allowed}, got {value!r}$"
    with pytest.raises(ValueError, match=message):
        train_config(**{field: value})


def test_the_registry_gives_each_algorithm_its_own_settings_class():
    assert {algo: config.algo for algo, config in ALGORITHMS.items()} == {
        "mapoca": "mapoca",
        "mappo": "mappo",
        "ippo": "ippo",
    }
    assert TrainConfig().algo == "mapoca"
    ppo = {field.name for field in dataclasses.fields(MAPPOConfig)}
    assert LOSS_FIELDS - ppo == {"baseline_coeff", "teacher_coeff", "teacher_coeff_end"} | {
        "teacher_iterations"
    }
    # what MAPPO's and IPPO's advantages need, they require
    with pytest.raises(ValueError, match=r"^loss.value_coeff must be a finite number > 0, got 0"):
        train_config(algo="mappo", value_coeff=0)
    assert train_config(algo="mapoca", value_coeff=0).loss.value_coeff == 0


@pytest.mark.parametrize("setting", ["teacher_coeff", "baseline_coeff", "teacher_iterations"])
@pytest.mark.parametrize("algo", ["mappo", "ippo"])
def test_a_setting_of_mapoca_is_not_one_of_another_algorithm(algo, setting):
    with pytest.raises(TypeError, match=setting):  # by construction: no such field
        ALGORITHMS[algo](**{setting: 1.0})
    refused = rf"^loss.{setting} is not a setting of algo={algo}; its loss settings are: gamma, "
    with pytest.raises(ValueError, match=refused):
        loss_config({"algo": algo, setting: 1.0})
    with pytest.raises(ValueError, match=refused):  # also through the loss group's presets
        RecipeConfig.of(composed(f"algo={algo}", f"+loss.{setting}=1"))


@pytest.mark.parametrize("algo", ["sac", "MAPPO", 3, None])
def test_an_unknown_algorithm_is_refused_naming_the_setting_and_the_choices(algo):
    with pytest.raises(ValueError, match=r"^loss\.algo must be one of mapoca, mappo, ippo"):
        loss_config({"algo": algo})


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        (["+foo=1"], "^foo is not a setting; the config groups are: env, model, train, run"),
        (["+run.foo=1"], "^run.foo is not a setting; the settings of run are: name, seed"),
        (["+train.foo=1"], "^train.foo is not a setting"),
        (["+env.foo=1"], "^env.foo is not a setting"),
        (["+model.foo=1"], "^model.foo is not a setting"),
        (["+logger.foo=1"], "^logger.foo is not a setting"),
        (["train.cuda_graphs=2"], "^train.cuda_graphs must be true or false, got 2$"),
        (["env.wrap_edges=1"], "^env.wrap_edges must be true or false, got 1$"),
        (["run.eval_sampled=yes"], "^run.eval_sampled must be true or false, got 'yes'$"),
        (["model.relative_objects=0"], "^model.relative_objects must be true or false, got 0$"),
        (["run.seed=-1"], r"^run.seed must be an integer in \[0, 2\*\*64\), got -1$"),
        (["run.seed=18446744073709551616"], r"^run.seed must be an integer in \[0, 2\*\*64\)"),
        (["run.name=../../x"], "^run.name must be a name of 1 to 100 letters, digits"),
        (["run.name=" + "x" * 101], "^run.name must be a name of 1 to 100 letters"),
        (["run.resume=''"], "^run.resume must be a non-empty path or null"),
        (["run.minutes=0"], r"^run.minutes must be a finite number > 0 or null \(no time"),
        (["run.device=gpu"], "^run.device must be auto, cpu, cuda or cuda:<index>, got 'gpu'$"),
        (["model.dropout=1.5"], r"^model.dropout must be a finite number in \[0, 1\), got 1.5$"),
        (["model.embed_dim=0"], "^model.embed_dim must be an integer >= 1, got 0$"),
        (["env.grid_size=1"], "^env.grid_size must be an integer >= 2, got 1$"),
        (["logger.kind=stdout"], "^logger.kind must be one of wandb, csv, tensorboard, none"),
    ],
)
def test_a_bad_setting_of_the_recipes_is_refused_by_its_key(overrides, message):
    with pytest.raises(ValueError, match=message):
        RecipeConfig.of(composed(*overrides))


def test_every_recipe_config_builds_its_settings():
    for name in ("mapoca_pretrain", "mapoca_finetune", "mapoca_paper", "smoke"):
        settings = RecipeConfig.of(composed(config=name))
        assert settings.run.name == name
    default = RecipeConfig.of(composed(config="mapoca_pretrain"))
    assert default.run == RunConfig(name="mapoca_pretrain")  # the run group is RunConfig's


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        (["+foo=1"], "^foo is not a setting; the settings of the top level are: env, checkpoint"),
        (["+video.foo=1"], "^video.foo is not a setting"),
        (["respawn=1"], "^respawn must be true or false, got 1$"),
        (["video.format=avi"], "^video.format must be one of mp4, gif, got 'avi'$"),
        (["episodes=0"], "^episodes must be an integer >= 1, got 0$"),
    ],
)
def test_a_bad_setting_of_the_evaluation_recipe_is_refused_by_its_key(overrides, message):
    with pytest.raises(ValueError, match=message):
        EvaluateConfig.of(composed(*overrides, config="evaluate"))


def test_an_integer_for_a_float_becomes_a_float_and_lists_are_checked_by_item():
    settings = RecipeConfig.of(composed("env.approach_scale=0", "loss.gamma=1"))
    assert type(settings.env.approach_scale) is float and type(settings.train.loss.gamma) is float
    with pytest.raises(ValueError, match=r"^model.cnn_channels must be a list of 1 to 8 integers"):
        RecipeConfig.of(composed("model.cnn_channels=[4,8.5,8]"))
    with pytest.raises(ValueError, match=r"^run.cpu_defaults must be a list of overrides"):
        check_value("run.cpu_defaults", ["model"], list[str], OVERRIDES)
    assert build(RunConfig, {"minutes": 2}, "run").minutes == 2.0


def _imports(name: str, path: Path, modules: set[str]) -> set[str]:
    """The package's modules that module ``name`` imports when it is imported (not those under
    ``if TYPE_CHECKING``), its own packages' ``__init__`` aside (a package's file imports its
    modules; a module reaching its package is that, not a circle)."""
    tree = ast.parse(path.read_text())
    for node in ast.walk(tree):
        if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test):
            node.body = []
    imported = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            for alias in node.names:
                module = f"{node.module}.{alias.name}"
                imported.add(module if module in modules else node.module)
        elif isinstance(node, ast.Import):
            imported |= {alias.name for alias in node.names}
    return {
        module
        for module in imported & modules
        if module != name and not name.startswith(f"{module}.")
    }


def test_no_import_circle_in_the_package():
    paths = {
        ".".join(path.relative_to(ROOT).with_suffix("").parts).removesuffix(".__init__"): path
        for path in PACKAGE.rglob("*.py")
    }
    edges = {name: _imports(name, path, set(paths)) for name, path in paths.items()}
    circles, done = [], set()

    def visit(name: str, path: list[str]) -> None:
        for target in edges[name]:
            if target in path:
                circles.append([*path[path.index(target) :], target])
            elif target not in done:
                visit(target, [*path, target])
        done.add(name)

    for name in sorted(edges):
        if name not in done:
            visit(name, [name])
    assert circles == []
    assert "terrashift_rl.training.trainer" not in edges["terrashift_rl.training.algorithms"]
