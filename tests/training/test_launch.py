"""What the recipes share around the loop: which CPU-sized defaults apply, the device setting,
Warp's start, a checkpoint's actions, the stop request, the best window, Inductor's compile
workers at the end."""

import signal
import subprocess
import sys
import time

import pytest
import torch
import warp as wp
from omegaconf import OmegaConf

from terrashift_rl.sim import TerraShiftConfig
from terrashift_rl.training import load_checkpoint
from terrashift_rl.training.checkpoint import check_action_mode, update_best
from terrashift_rl.training.launch import (
    close_compile_workers,
    cpu_overrides,
    refusals_end_the_run,
    resolve_device,
    size_for_the_machine,
    start_warp,
)
from terrashift_rl.training.signals import StopRequest

DEFAULTS = ["model=small", "train.num_envs=32", "run.eval_episodes=16"]


@pytest.mark.parametrize(
    ("given", "kept"),
    [
        ([], DEFAULTS),
        (["env=finetune", "run.seed=3", "logger=csv"], DEFAULTS),
        (["train.num_envs=8"], ["model=small", "run.eval_episodes=16"]),
        (["model=medium"], ["train.num_envs=32", "run.eval_episodes=16"]),
        (["model.embed_dim=64"], ["train.num_envs=32", "run.eval_episodes=16"]),
        (["+model.dropout=0.05"], ["train.num_envs=32", "run.eval_episodes=16"]),
        (["train=throughput"], ["model=small", "run.eval_episodes=16"]),
        (["~run.eval_episodes"], ["model=small", "train.num_envs=32"]),
        (["train.num_envs_per_gpu=1"], DEFAULTS),  # a key that only starts like one
    ],
)
def test_a_cpu_default_applies_unless_the_command_line_sets_its_key_or_group(given, kept):
    assert cpu_overrides(DEFAULTS, given) == kept


@pytest.mark.parametrize(
    ("value", "shown"),
    [("model=small", "'model=small'"), (["model"], r"\['model'\]"), ([3], r"\[3\]")],
)
def test_cpu_defaults_that_are_not_overrides_are_refused_naming_the_key(monkeypatch, value, shown):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    cfg = OmegaConf.create({"run": {"device": "auto", "cpu_defaults": value}})
    message = f"^run.cpu_defaults must be a list of overrides \\(key=value\\), got {shown}$"
    with pytest.raises(ValueError, match=message):
        size_for_the_machine(cfg, device_key="run.device", defaults_key="run.cpu_defaults")


@pytest.mark.parametrize(("device", "cuda"), [("cpu", False), ("cuda:0", True), ("auto", True)])
def test_only_auto_on_a_machine_without_cuda_is_sized_for_the_cpu(monkeypatch, device, cuda):
    # outside a Hydra app, sizing would fail reading the command line: it must not try
    monkeypatch.setattr(torch.cuda, "is_available", lambda: cuda)
    cfg = OmegaConf.create({"run": {"device": device, "cpu_defaults": DEFAULTS}})
    sized = size_for_the_machine(cfg, device_key="run.device", defaults_key="run.cpu_defaults")
    assert sized is cfg


def test_auto_resolves_to_the_cpu_without_cuda(monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert resolve_device("auto", "run.device") == torch.device("cpu")
    with pytest.raises(ValueError, match="^device must be auto, cpu, cuda or cuda:<index>, got 7"):
        resolve_device(7, "device")


def test_a_kernel_cache_without_the_simulators_kernels_is_announced(monkeypatch, tmp_path, caplog):
    wp.init()  # with the real cache, which the test then hides
    monkeypatch.setattr(wp.config, "kernel_cache_dir", str(tmp_path))
    with caplog.at_level("INFO"):
        start_warp(torch.device("cpu"))  # a first run: the compile's wait is explained
        (tmp_path / "wp_terrashift_rl.sim.simulator_609b2de").mkdir()
        start_warp(torch.device("cpu"))  # later runs load the kernels: nothing to say
    assert caplog.messages == [
        f"Warp compiles the simulator's kernels into {tmp_path} before the first step, once (on "
        "two CPU cores about 10 s; later runs load them)"
    ]


def test_a_ctrl_c_outside_the_runs_own_handler_ends_it_in_one_line(monkeypatch, caplog):
    monkeypatch.delenv("HYDRA_FULL_ERROR", raising=False)
    with caplog.at_level("INFO"), pytest.raises(SystemExit) as ended, refusals_end_the_run():
        raise KeyboardInterrupt  # during set-up or an evaluation: no traceback
    assert ended.value.code == 130
    assert caplog.messages == ["interrupted"]
    monkeypatch.setenv("HYDRA_FULL_ERROR", "1")
    with pytest.raises(KeyboardInterrupt), refusals_end_the_run():
        raise KeyboardInterrupt  # kept, with its traceback, where Hydra keeps its errors'


def test_a_checkpoint_is_refused_on_a_scene_with_other_actions():
    shape = {"env_config": {"action_mode": "shape"}}
    check_action_mode(shape, TerraShiftConfig(action_mode="shape"), "run.pretrained")
    with pytest.raises(ValueError, match="run.pretrained was trained with env.action_mode=shape"):
        check_action_mode(shape, TerraShiftConfig(), "run.pretrained")


def test_a_second_signal_interrupts_at_once():
    before = {number: signal.getsignal(number) for number in (signal.SIGINT, signal.SIGTERM)}
    with StopRequest(announce=False) as stop:
        assert signal.getsignal(signal.SIGTERM) is stop
        stop(signal.SIGTERM, None)
        assert stop.requested
        with pytest.raises(KeyboardInterrupt):
            stop(signal.SIGINT, None)
    assert {number: signal.getsignal(number) for number in before} == before


def test_a_signal_in_a_skippable_step_skips_it_and_only_it(caplog):
    finished = []
    with caplog.at_level("INFO"), StopRequest() as stop:
        with stop.skippable("the final evaluation"):
            stop(signal.SIGINT, None)
            finished.append("the final evaluation")
        assert not stop.requested  # the run was not asked to stop: the step was skipped
        stop(signal.SIGINT, None)  # outside it, the first signal asks to stop
        assert stop.requested
    assert finished == []
    assert caplog.messages == [
        "the final evaluation skipped",
        "SIGINT: stopping after this iteration, then saving a checkpoint to resume from (signal "
        "again to quit at once, without it)",
    ]


def test_the_best_window_writes_best_pt_only_when_its_mean_is_the_highest_yet(tmp_path):
    class Trainer:  # what weights_state reads
        iteration, env_steps = 3, 96

        def weights_state_dict(self):
            return {"networks": torch.nn.Linear(1, 1).state_dict(), "algo": "mapoca"}

    best = {"reward": -float("inf"), "recent": []}
    path = tmp_path / "best.pt"
    update_best(best, 1.0, 2, Trainer(), {}, path)
    assert not path.exists()  # the window is not full yet
    update_best(best, 3.0, 2, Trainer(), {}, path)
    assert best == {"reward": 2.0, "recent": [1.0, 3.0]}
    saved = load_checkpoint(path)
    assert (saved["mean_reward_per_decision"], saved["iteration"]) == (2.0, 3)
    assert saved["algo"] == "mapoca" and "weight" in saved["networks"]
    path.unlink()
    update_best(best, 0.0, 2, Trainer(), {}, path)
    assert best["reward"] == 2.0 and best["recent"] == [3.0, 0.0] and not path.exists()


class SidecarPool:
    """A compile-worker pool as Inductor's ``SubprocPool`` is to its shutdown: a sidecar process
    that it waits for, which exits when told to, or not at all (``hangs``)."""

    def __init__(self, *, hangs: bool) -> None:
        self.process = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(120)"])
        self.hangs = hangs

    def shutdown(self) -> None:
        if not self.hangs:
            self.process.terminate()
        self.process.wait(300)


@pytest.mark.parametrize("hangs", [False, True])
def test_compile_workers_that_do_not_exit_are_killed_after_the_timeout(monkeypatch, caplog, hangs):
    from torch._inductor import async_compile

    pool = SidecarPool(hangs=hangs)
    monkeypatch.setattr(async_compile, "_pool_set", [pool])
    try:
        start = time.monotonic()
        exited = close_compile_workers(timeout=1.0)
        seconds = time.monotonic() - start
        ended = pool.process.poll() is not None
    finally:
        pool.process.kill()
    assert exited is not hangs
    assert ended and seconds < 10.0
    assert async_compile._pool_set == []  # Inductor's own shutdown ran: none is left for exit
    warned = "compile workers had not exited 1 s after the run" in caplog.text
    assert warned is hangs


def test_without_compile_workers_nothing_is_waited_for(monkeypatch):
    from torch._inductor import async_compile

    monkeypatch.setattr(async_compile, "_pool_set", [])
    assert close_compile_workers(timeout=0.0)
