"""Hostile checkpoints: files that torch.load accepts with weights_only but that no run wrote.
Each is refused before anything is built from it, in one message naming the file, the entry and
what it must be; nothing in a checkpoint is parsed as text or interpolated."""

import dataclasses
import os
import sys
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig
from test_hostile_settings import refused_in_subprocess
from test_settings import ROOT

from terrashift_rl.modules import TerraShiftModelConfig, make_terrashift_networks
from terrashift_rl.sim import TerraShiftConfig
from terrashift_rl.training import checkpoint as checkpoints
from terrashift_rl.training import load_checkpoint, save_checkpoint
from terrashift_rl.training.launch import size_for_the_machine
from terrashift_rl.training.settings import register_config_schemas

SMALL = TerraShiftModelConfig.small()


@pytest.fixture(scope="module")
def weights() -> dict:
    torch.manual_seed(0)
    return make_terrashift_networks(SMALL).state_dict()


def weights_checkpoint(weights: dict, **entries) -> dict:
    """What a run writes for evaluation (best.pt, snapshots), with ``entries`` replaced."""
    return {
        "networks": weights,
        "algorithm_networks": {},
        "algo": "mapoca",
        "env_config": dataclasses.asdict(TerraShiftConfig()),
        "model_config": dataclasses.asdict(SMALL),
        "iteration": 1,
        "env_steps": 96,
        **entries,
    }


def refusal(path, expected: str) -> str:
    """The refusal of the checkpoint at ``path``: one line naming the file and ``expected``."""
    with pytest.raises(ValueError) as error:
        load_checkpoint(path)
    message = str(error.value)
    assert str(path) in message and expected in message, message
    assert len(message.splitlines()) == 1
    return message


def test_a_written_checkpoint_loads_with_its_settings_as_the_room_writes_them(tmp_path, weights):
    state = weights_checkpoint(weights, env_config={"grid_size": 15, "action_mode": "shape"})
    loaded = load_checkpoint(save_checkpoint(state, tmp_path / "best.pt"))
    assert loaded["env_config"] == dataclasses.asdict(TerraShiftConfig(action_mode="shape"))
    assert loaded["model_config"] == dataclasses.asdict(SMALL)
    assert all(torch.equal(loaded["networks"][k], v) for k, v in weights.items())


def test_a_resume_checkpoint_without_an_entry_resuming_reads_is_refused_naming_it(
    tmp_path, weights
):
    path = save_checkpoint(weights_checkpoint(weights), tmp_path / "last.pt")
    with pytest.raises(ValueError) as error:
        load_checkpoint(path, required=checkpoints.RESUME_KEYS)
    message = str(error.value)
    assert str(path) in message and "logger_run_id" in message and "optimizer" in message
    assert len(message.splitlines()) == 1


def test_a_list_nested_3000_deep_is_one_refusal_not_a_recursion_error(tmp_path):
    nested = []
    for _ in range(3000):
        nested = [nested]
    limit = sys.getrecursionlimit()
    sys.setrecursionlimit(10_000)  # torch.save's pickler recurses; the loader must not
    try:
        torch.save({"networks": nested}, tmp_path / "deep.pt")
    finally:
        sys.setrecursionlimit(limit)
    refusal(tmp_path / "deep.pt", f"nests lists or dicts more than {checkpoints.MAX_DEPTH} deep")


def test_more_entries_than_the_limit_are_refused(tmp_path, monkeypatch):
    torch.save({"iteration": list(range(50))}, tmp_path / "wide.pt")
    monkeypatch.setattr(checkpoints, "MAX_ENTRIES", 40)
    refusal(tmp_path / "wide.pt", "holds more than 40 entries")


def test_a_checkpoint_larger_than_the_memory_is_refused_before_it_is_read(tmp_path, monkeypatch):
    torch.save({"iteration": torch.zeros(1000)}, tmp_path / "big.pt")
    monkeypatch.setattr(checkpoints, "_memory_bytes", lambda: 1000)
    refusal(tmp_path / "big.pt", "more than this machine's memory (1,000 bytes)")


@pytest.mark.parametrize(
    ("carry", "expected"),
    [
        ({"__tensordict__": 5}, "entry carry['__tensordict__']: must be a tensordict as"),
        (
            {"__tensordict__": {"batch_size": [3], "entries": {"x": torch.zeros(2)}}},
            "entry carry: is not a tensordict",
        ),
        (
            {"__tensordict__": {"batch_size": [-1], "entries": {}}},
            "entry carry['__tensordict__']: must be a tensordict",
        ),
    ],
)
def test_a_crafted_tensordict_is_refused_naming_its_entry(tmp_path, carry, expected):
    torch.save({"carry": carry}, tmp_path / "carry.pt")
    refusal(tmp_path / "carry.pt", expected)


@pytest.mark.parametrize(
    ("entries", "expected"),
    [
        ({"env_config": {**dataclasses.asdict(TerraShiftConfig()), "foo": 1}}, "env.foo is not"),
        ({"env_config": {"grid_size": 0}}, "env_config: env.grid_size must be an integer >= 2"),
        ({"env_config": {"wrap_edges": 2}}, "env.wrap_edges must be true or false, got 2"),
        ({"env_config": {"reward_normalizer": 1e-300}}, "env.reward_normalizer (1e-300) is 0"),
        ({"env_config": {"distance_scale": 1e308}}, "the reward would be infinite"),
        ({"env_config": {"column_shape": "${oc.env:HOME}"}}, "got '${oc.env:HOME}'"),
        ({"model_config": {"embed_dim": 0}}, "model_config: model.embed_dim must be an integer"),
        ({"model_config": {"dropout": 1.5}}, "model.dropout must be a finite number in [0, 1)"),
        ({"model_config": {"distribution": "${oc.env:HOME}"}}, "got '${oc.env:HOME}'"),
        ({"model_config": {"distribution": "beta model.embed_dim=8"}}, "model.distribution"),
        ({"model_config": {"embed_dim": 10**7}}, "model: the networks would hold 7.2e+15 param"),
        ({"model_config": {"trunk_layers": 10**6}}, "model.trunk_layers must be an integer in"),
        ({"model_config": "embed_dim=64"}, "entry model_config: must be a dict, got a str"),
        ({"model_config": {3: 64}}, "entry model_config: must be a mapping of setting names"),
        ({"algo": ["mapoca"]}, "entry algo: must be a str, got a list"),
        ({"algo": "sac"}, "entry algo: must be one of mapoca, mappo, ippo, got 'sac'"),
        ({"shell": "rm -rf /"}, "entry 'shell': is not an entry of a checkpoint"),
        ({"train_config": {"loss": {"value_coeff": 1e308}}}, "loss.value_coeff (1e+308) times"),
        ({"train_config": {"loss": 1}}, "train.loss must be a mapping of settings, got 1"),
        ({"best": {"reward": "x", "recent": []}}, "entry best: must be {'reward': a number"),
    ],
)
def test_a_stored_setting_passes_the_settings_room_or_is_refused_naming_it(
    tmp_path, weights, entries, expected
):
    path = save_checkpoint(weights_checkpoint(weights, **entries), tmp_path / "last.pt")
    message = refusal(path, expected)
    assert os.environ.get("HOME", "/root") not in message.replace(str(tmp_path), "")


def test_weights_that_do_not_fit_the_stored_model_are_refused_naming_the_tensor(tmp_path, weights):
    bigger = dataclasses.asdict(dataclasses.replace(SMALL, embed_dim=64, num_heads=4))
    path = save_checkpoint(weights_checkpoint(weights, model_config=bigger), tmp_path / "x.pt")
    refusal(path, "model_config's network has [64")
    missing = {name: value for name, value in weights.items() if "policy" not in name}
    path = save_checkpoint(weights_checkpoint(missing), tmp_path / "y.pt")
    refusal(path, "is missing: model_config's network has a")
    extra = {**weights, "backdoor": torch.zeros(1)}
    path = save_checkpoint(weights_checkpoint(extra), tmp_path / "z.pt")
    refusal(path, "entry networks['backdoor']: is not a weight of model_config's network")


def test_non_finite_weights_are_refused_naming_the_tensor(tmp_path, weights):
    name = next(iter(weights))
    broken = {**weights, name: torch.full_like(weights[name], float("nan"))}
    path = save_checkpoint(weights_checkpoint(broken), tmp_path / "nan.pt")
    refusal(path, f"entry networks[{name!r}]: holds NaN or infinite values")
    optimizer = {"state": {0: {"exp_avg": torch.tensor([float("inf")])}}, "param_groups": []}
    path = save_checkpoint(weights_checkpoint(weights, optimizer=optimizer), tmp_path / "opt.pt")
    refusal(path, "entry optimizer['state'][0]['exp_avg']: holds NaN or infinite values")


def sized_from(pretrained: Path) -> DictConfig:
    """The smoke config with ``run.pretrained`` on a CPU, sized in Hydra's app context (as
    ``@hydra.main`` sets it) for a run of that checkpoint."""
    register_config_schemas()
    configs = str(ROOT / "recipes" / "configs")
    with initialize_config_dir(config_dir=configs, version_base=None):
        overrides = [f"run.pretrained={pretrained}", "run.device=cpu"]
        cfg = compose("smoke", overrides, return_hydra_config=True)
        HydraConfig.instance().set_config(cfg)
        try:
            return size_for_the_machine(
                cfg,
                device_key="run.device",
                defaults_key="run.cpu_defaults",
                model_from=("run.resume", "run.pretrained"),
            )
        finally:
            HydraConfig.instance().cfg = None


def test_a_run_from_a_checkpoint_takes_its_model_as_checked_data_not_as_overrides(
    tmp_path, monkeypatch
):
    model = dataclasses.replace(SMALL, critic_hidden_dim=24, cnn_channels=[4, 8, 12])
    weights = make_terrashift_networks(model).state_dict()
    state = weights_checkpoint(weights, model_config=dataclasses.asdict(model))
    sized = sized_from(save_checkpoint(state, tmp_path / "good.pt"))
    assert sized.model.critic_hidden_dim == 24 and list(sized.model.cnn_channels) == [4, 8, 12]

    monkeypatch.setenv("HOSTILE_SECRET", "the-secret")
    hostile = dict(dataclasses.asdict(model), distribution="${oc.env:HOSTILE_SECRET}")
    path = save_checkpoint({**state, "model_config": hostile}, tmp_path / "bad.pt")
    with pytest.raises(ValueError) as error:
        sized_from(path)
    assert str(path) in str(error.value) and "'${oc.env:HOSTILE_SECRET}'" in str(error.value)
    assert "the-secret" not in str(error.value)


@pytest.mark.slow
def test_evaluation_refuses_weights_that_do_not_fit_their_model_in_one_message(tmp_path, weights):
    other = dataclasses.asdict(dataclasses.replace(SMALL, policy_hidden_dim=40))
    path = save_checkpoint(weights_checkpoint(weights, model_config=other), tmp_path / "x.pt")
    stderr = refused_in_subprocess(
        "evaluate.py", f"checkpoint={path}", "device=cpu", cwd=tmp_path, config="evaluate"
    )
    assert f"checkpoint {path}, entry networks[" in stderr
    assert "model_config's network has [40" in stderr
