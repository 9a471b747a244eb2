"""Filesystem faults: a run folder in use by a live run, folders that cannot be written, a disk
that fills mid-write, an unusable Warp kernel cache. Each is one message naming the file or
folder; a failed write keeps the previous checkpoint."""

import errno
import os
import subprocess
import sys

import pytest
import torch
from test_hostile_settings import refused_in_subprocess

from terrashift_rl.training import checkpoint as checkpoints
from terrashift_rl.training import load_checkpoint, save_checkpoint
from terrashift_rl.training.launch import (
    LOCK_NAME,
    check_warp_cache,
    claim_run_folder,
    refusals_end_the_run,
)


def dead_pid() -> int:
    """The process id of a process that has ended."""
    process = subprocess.Popen([sys.executable, "-c", "pass"])
    process.wait()
    return process.pid


def test_a_run_folder_is_held_while_the_run_goes_on_and_freed_after(tmp_path):
    with claim_run_folder(tmp_path):
        assert (tmp_path / LOCK_NAME).read_text() == str(os.getpid())
        with pytest.raises(ValueError) as error, claim_run_folder(tmp_path):
            pass
        message = str(error.value)
        assert message.startswith(f"the run folder {tmp_path} is in use by the run of process")
        assert str(os.getpid()) in message and LOCK_NAME in message
    assert not (tmp_path / LOCK_NAME).exists()
    assert (tmp_path / "checkpoints").is_dir()


def test_a_live_run_holds_its_folder_and_a_killed_one_frees_it(tmp_path):
    holder = subprocess.Popen(
        [sys.executable, "-c", HOLDS_THE_FOLDER, str(tmp_path)], stdout=subprocess.PIPE, text=True
    )
    try:
        assert holder.stdout.readline() == "holding\n"
        in_use = f"in use by the run of process {holder.pid} "
        with pytest.raises(ValueError, match=in_use), claim_run_folder(tmp_path):
            pass
    finally:
        holder.kill()  # SIGKILL: the run gets no chance to remove its lock file
        holder.wait()
    assert (tmp_path / LOCK_NAME).read_text() == str(holder.pid)
    with claim_run_folder(tmp_path):
        assert (tmp_path / LOCK_NAME).read_text() == str(os.getpid())


HOLDS_THE_FOLDER = """
import sys, time
from terrashift_rl.training.launch import claim_run_folder
with claim_run_folder(sys.argv[1]):
    print("holding", flush=True)
    time.sleep(600)
"""


def test_the_lock_is_freed_when_the_run_fails(tmp_path):
    with pytest.raises(RuntimeError), claim_run_folder(tmp_path):
        raise RuntimeError("the run failed")
    assert not (tmp_path / LOCK_NAME).exists()


@pytest.mark.parametrize(
    "left",
    [
        lambda: str(dead_pid()),  # a killed run's
        lambda: str(os.getpid()),  # a killed run's process id, reused by a live process
        lambda: "",  # killed between creating and writing it
    ],
)
def test_a_lock_left_by_a_run_that_is_gone_is_taken_over(tmp_path, left):
    (tmp_path / LOCK_NAME).write_text(left())
    with claim_run_folder(tmp_path):
        assert (tmp_path / LOCK_NAME).read_text() == str(os.getpid())
    assert not (tmp_path / LOCK_NAME).exists()


def test_a_run_folder_that_cannot_be_written_is_refused_at_start_up(tmp_path):
    (tmp_path / "checkpoints").write_text("a file where the folder should be")
    with pytest.raises(ValueError) as error, claim_run_folder(tmp_path):
        pass
    assert str(error.value).startswith(
        f"the checkpoints folder {tmp_path / 'checkpoints'} cannot be written ("
    )
    assert not (tmp_path / LOCK_NAME).exists()
    with (
        pytest.raises(ValueError, match="^the run folder .* cannot be written"),
        claim_run_folder(tmp_path / "checkpoints" / "run"),
    ):
        pass


def test_a_full_disk_names_the_checkpoint_keeps_the_previous_one_and_leaves_no_temporary(
    tmp_path, monkeypatch
):
    last = save_checkpoint({"iteration": 1}, tmp_path / "last.pt")
    save = torch.save

    def disk_full_mid_write(state, file):
        save(state, file)
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(checkpoints.torch, "save", disk_full_mid_write)
    with pytest.raises(OSError) as error:
        save_checkpoint({"iteration": 2}, last)
    assert str(error.value) == (
        f"checkpoint {last} could not be written (No space left on device); the previous one "
        "is kept"
    )
    assert load_checkpoint(last)["iteration"] == 1
    assert [path.name for path in tmp_path.iterdir()] == ["last.pt"]


def test_a_checkpoint_in_a_folder_that_cannot_be_made_is_named(tmp_path):
    (tmp_path / "checkpoints").write_text("a file")
    path = tmp_path / "checkpoints" / "last.pt"
    with pytest.raises(OSError, match=f"^checkpoint {path} could not be written .*no earlier one"):
        save_checkpoint({"iteration": 1}, path)


def test_a_refusal_ends_the_run_with_its_message_alone(monkeypatch):
    monkeypatch.delenv("HYDRA_FULL_ERROR", raising=False)
    for error in (ValueError("run.seed must be ..."), OSError("checkpoint x could not be ...")):
        with pytest.raises(SystemExit) as ended, refusals_end_the_run():
            raise error
        assert ended.value.code == f"error: {error}"
    monkeypatch.setenv("HYDRA_FULL_ERROR", "1")
    with pytest.raises(ValueError), refusals_end_the_run():
        raise ValueError("kept with its traceback")


def test_an_unusable_warp_cache_is_named(tmp_path, monkeypatch):
    monkeypatch.delenv("WARP_CACHE_PATH", raising=False)
    check_warp_cache()
    (tmp_path / "file").write_text("")
    monkeypatch.setenv("WARP_CACHE_PATH", str(tmp_path / "file" / "cache"))
    with pytest.raises(ValueError) as error:
        check_warp_cache()
    assert str(error.value).startswith(f"WARP_CACHE_PATH, Warp's kernel cache, at {tmp_path}")
    assert str(error.value).endswith("; set it to a writable folder or unset it")


@pytest.mark.slow
def test_a_recipe_refuses_a_folder_in_use_and_an_unusable_warp_cache_in_one_message(tmp_path):
    run = tmp_path / "run"
    with claim_run_folder(run):  # this process's run holds the folder
        stderr = refused_in_subprocess("mapoca_pretrain.py", cwd=tmp_path)
    assert f"is in use by the run of process {os.getpid()}" in stderr
    assert not (run / "config.yaml").exists() and not any((run / "checkpoints").iterdir())

    (run / "file").write_text("")
    env = {**os.environ, "WARP_CACHE_PATH": str(run / "file" / "cache")}
    stderr = refused_in_subprocess("mapoca_pretrain.py", cwd=tmp_path, env=env)
    assert "WARP_CACHE_PATH, Warp's kernel cache, at" in stderr
