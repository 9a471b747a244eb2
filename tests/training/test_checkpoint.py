"""Checkpoints: loading runs no code, unreadable files are named, a trainer's state round-trips."""

import os
import pickle
import random
import subprocess
import sys
import time
import zipfile

import pytest
import torch
from tensordict import TensorDict
from torch.serialization import get_unsafe_globals_in_checkpoint

from terrashift_rl.training import load_checkpoint, save_checkpoint
from terrashift_rl.training.checkpoint import (
    CONVERT_COMMAND,
    STALE_AFTER_S,
    remove_stale_temporaries,
)


class CreatesAFile:
    """Unpickling this calls ``open(path, "w")``: what a crafted checkpoint could run."""

    def __init__(self, path):
        self.path = str(path)

    def __reduce__(self):
        return (open, (self.path, "w"))


def carried_state() -> TensorDict:
    """A tensordict shaped like the trainer's carry: a nested group with its own batch size."""
    agents = TensorDict({"action": torch.randn(3, 4, 6)}, batch_size=[3, 4])
    return TensorDict({"agents": agents, "done": torch.zeros(3, 1, dtype=torch.bool)}, [3])


def test_a_checkpoint_that_would_run_code_is_refused_and_runs_nothing(tmp_path):
    target = tmp_path / "created_by_loading"
    path = tmp_path / "crafted.pt"
    torch.save({"networks": CreatesAFile(target)}, path)
    with pytest.raises(ValueError, match=f"refused to load {path}: loading it would call") as no:
        load_checkpoint(path)
    assert "must not run code" in str(no.value)
    assert not target.exists()
    torch.load(path, weights_only=False)["networks"].close()  # as loading was: the file is made
    assert target.exists()


def test_a_crafted_plain_pickle_is_not_unpickled(tmp_path):
    target = tmp_path / "created_by_loading"
    path = tmp_path / "crafted.pt"
    path.write_bytes(pickle.dumps(CreatesAFile(target)))
    with pytest.raises(ValueError, match=f"checkpoint {path} .* is not a zip archive"):
        load_checkpoint(path)
    assert not target.exists()
    pickle.loads(path.read_bytes()).close()
    assert target.exists()


@pytest.mark.parametrize(
    "content", [b"", bytes(random.Random(0).getrandbits(8) for _ in range(4096)), b"text\n"]
)
def test_an_unreadable_file_is_named_with_what_is_wrong(tmp_path, content):
    path = tmp_path / "bad.pt"
    path.write_bytes(content)
    with pytest.raises(ValueError, match=f"checkpoint {path} .* is not a zip archive"):
        load_checkpoint(path)


def test_a_truncated_checkpoint_is_named(tmp_path):
    path = save_checkpoint({"networks": {"w": torch.randn(1000)}}, tmp_path / "last.pt")
    path.write_bytes(path.read_bytes()[:2000])
    with pytest.raises(ValueError, match=f"checkpoint {path} .* is truncated"):
        load_checkpoint(path)


def test_a_corrupt_archive_is_named(tmp_path):
    path = save_checkpoint({"networks": {"w": torch.zeros(1000)}}, tmp_path / "last.pt")
    archive = bytearray(path.read_bytes())
    start = archive.index(bytes(400))  # inside the zeroed tensor's bytes
    archive[start : start + 400] = b"x" * 400
    path.write_bytes(archive)
    with pytest.raises(ValueError, match=f"checkpoint {path} is corrupt: its record .* fails"):
        load_checkpoint(path)


def test_a_foreign_file_is_named_with_what_it_holds(tmp_path):
    archive = tmp_path / "photos.pt"
    with zipfile.ZipFile(archive, "w") as photos:
        photos.writestr("photo.txt", "not a tensor")
    with pytest.raises(ValueError, match=f"checkpoint {archive} is not a PyTorch archive"):
        load_checkpoint(archive)
    tensor = tmp_path / "tensor.pt"
    torch.save(torch.zeros(3), tensor)
    with pytest.raises(ValueError, match=f"{tensor} holds a Tensor, not a checkpoint"):
        load_checkpoint(tensor)
    weights = save_checkpoint({"networks": {}, "env_steps": 3}, tmp_path / "best.pt")
    with pytest.raises(ValueError, match=r"best.pt lacks \['optimizer'\]; it holds"):
        load_checkpoint(weights, required=("networks", "optimizer"))
    with pytest.raises(FileNotFoundError, match="no checkpoint at"):
        load_checkpoint(tmp_path / "missing.pt")


def test_a_tensordict_round_trips_exactly_and_needs_no_pickled_class(tmp_path):
    carry = carried_state()
    state = {"carry": carry, "rng": torch.get_rng_state(), "best": {"recent": [0.5]}}
    path = save_checkpoint(state, tmp_path / "last.pt")
    assert get_unsafe_globals_in_checkpoint(path) == []
    loaded = load_checkpoint(path)
    assert loaded["carry"].batch_size == carry.batch_size
    assert loaded["carry"]["agents"].batch_size == carry["agents"].batch_size
    assert set(loaded["carry"].keys(True, True)) == set(carry.keys(True, True))
    for key, value in carry.items(True, True):
        assert (
            torch.equal(loaded["carry"][key], value) and loaded["carry"][key].dtype == value.dtype
        )
    assert torch.equal(loaded["rng"], state["rng"]) and loaded["best"] == state["best"]


def test_a_checkpoint_with_a_pickled_tensordict_converts_with_the_documented_command(tmp_path):
    path = tmp_path / "old.pt"
    torch.save({"carry": carried_state(), "iteration": 4}, path)  # as earlier versions wrote
    with pytest.raises(ValueError, match="would call tensordict") as refused:
        load_checkpoint(path)
    assert CONVERT_COMMAND in str(refused.value)
    command = CONVERT_COMMAND.replace("<file>", str(path)).replace("python", sys.executable, 1)
    subprocess.run(command, shell=True, check=True, capture_output=True)
    converted = load_checkpoint(path)
    assert converted["iteration"] == 4 and converted["carry"]["agents"].batch_size == (3, 4)


def test_only_temporary_files_left_untouched_are_removed(tmp_path):
    last = save_checkpoint({"iteration": 1}, tmp_path / "last.pt")
    stale, fresh = tmp_path / ".last.pt.killed.tmp", tmp_path / ".last.pt.writing.tmp"
    stale.write_bytes(b"half a checkpoint")
    fresh.write_bytes(b"a write in progress")
    old = time.time() - 2 * STALE_AFTER_S
    os.utime(stale, (old, old))
    assert remove_stale_temporaries(tmp_path) == [stale]
    assert not stale.exists() and fresh.exists() and last.exists()


def test_the_converter_brings_an_earlier_layout_to_the_current_one_and_leaves_that_alone():
    from terrashift_rl.training.checkpoint import upgrade

    old = {
        "networks": {},
        "env_config": {"grid_size": 15},
        "model_config": {"embed_dim": 32, "policy_output_gain": 0.01},  # a retired setting
        "train_config": {"algo": "mappo", "num_envs": 8, "gamma": 0.9, "value_clip_end": 0.2},
        "optimizer": {},
        "curriculum_config": {"kind": "auto"},
    }
    new = upgrade(old)
    assert new["algo"] == "mappo" and new["algorithm_networks"] == {}
    assert new["env_config"] == {"action_mode": "delta", "grid_size": 15}
    assert new["model_config"] == {"embed_dim": 32}
    assert new["train_config"]["num_envs"] == 8 and "gamma" not in new["train_config"]
    assert new["train_config"]["loss"]["gamma"] == 0.9
    assert new["train_config"]["loss"]["clip_value_end"] == 0.2
    assert "teacher_coeff" not in new["train_config"]["loss"]  # MAPPO has none
    assert new["best"] == {"reward": -float("inf"), "recent": []}
    assert new["run_seconds"] == 0.0  # a resumed run's clock starts where none was kept
    # the schedules ran once, from the first iteration, before they could start again
    assert new["schedule_start"] == 0
    assert new["curriculum_config"] == {"restart_schedules": False, "kind": "auto"}
    assert upgrade(new) == new
    assert upgrade({"step": 1}) == {"step": 1}  # not a training checkpoint
