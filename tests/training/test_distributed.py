"""Data-parallel training: two gloo processes (two NCCL processes on a host with two GPUs) train
the smoke config, checkpoint and resume, with identical parameters after every update; each
splits its batch twice as finely as one process, or refuses a split it cannot make; the recipes
under torchrun; a rank that stops answering or dies ends the run with a message; the
process-group helpers in a single process."""

import importlib.util
import os
import re
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch
import torch.multiprocessing as mp
from hydra import compose, initialize_config_dir
from test_algorithms import eight_environments

from terrashift_rl.training import OnPolicyTrainer, distributed, load_checkpoint

ROOT = Path(__file__).resolve().parents[2]


def pretraining_recipe():
    """recipes/mapoca_pretrain.py as a module (it registers the config schemas)."""
    spec = importlib.util.spec_from_file_location(
        "mapoca_pretrain", ROOT / "recipes" / "mapoca_pretrain.py"
    )
    recipe = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(recipe)
    return recipe


CONFIGS = ROOT / "recipes" / "configs"
WORLD_SIZE = 2
FRAMES = 4 * 8  # the smoke config's environments x steps per iteration, per process


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def join(rank: int, port: int, device: str) -> None:
    """Joins the group of ``WORLD_SIZE`` processes at ``port`` as ``rank``, with the variables
    that torchrun would set."""
    os.environ.update(
        MASTER_ADDR="127.0.0.1",
        MASTER_PORT=str(port),
        RANK=str(rank),
        LOCAL_RANK=str(rank),
        WORLD_SIZE=str(WORLD_SIZE),
        LOCAL_WORLD_SIZE=str(WORLD_SIZE),
    )
    torch.set_num_threads(1)
    distributed.init_process_group(device, key="run.device")


def train_resume_and_record(rank: int, port: int, folder: Path, device: str) -> None:
    """One rank, as torchrun would start it: a straight run of 3 iterations (a), a run of 1
    (b) and b resumed to 3 (c), with the adaptive learning rate, on ``device`` (``cpu``: gloo;
    ``cuda``: NCCL, CUDA graphs and deterministic algorithms); after every update, this rank's
    parameters, return statistics and learning rates go to a file."""
    # joined once: the recipe's train() stays in a group it finds and leaves one it joined
    join(rank, port, device)
    updates = []
    train_iteration = OnPolicyTrainer.train_iteration

    def recorded(trainer: OnPolicyTrainer) -> dict[str, float]:
        metrics = train_iteration(trainer)
        parameters = [p.detach().reshape(-1) for _, p in trainer._named_parameters()]
        statistics = trainer.algorithm.value_normalizer.state_dict().values()
        rates = [float(group["lr"]) for group in trainer.optimizer.param_groups]
        updates.append(torch.cat([*parameters, *(s.reshape(1) for s in statistics)]).cpu())
        updates.append(torch.tensor(rates))
        return metrics

    OnPolicyTrainer.train_iteration = recorded
    recipe = pretraining_recipe()
    runs = {
        "a": [f"run.total_env_steps={3 * WORLD_SIZE * FRAMES}"],
        "b": [f"run.total_env_steps={WORLD_SIZE * FRAMES}"],
        "c": [
            f"run.total_env_steps={3 * WORLD_SIZE * FRAMES}",
            f"run.resume={folder}/b/checkpoints/last.pt",
        ],
    }
    with initialize_config_dir(config_dir=str(CONFIGS), version_base=None):
        for name, overrides in runs.items():
            overrides = [*overrides, "run.eval_every=2", "train.lr_schedule=adaptive"]
            overrides += [f"run.device={device}", f"train.deterministic={device == 'cuda'}"]
            cfg = compose(config_name="smoke", overrides=overrides)
            (folder / name).mkdir(exist_ok=True)  # as Hydra makes it
            recipe.train(cfg, run_dir=folder / name)
    # each exchange on values that differ between the ranks: rank r has r
    exchanged = {
        "average": distributed.average(torch.full((2,), float(rank), device=device)).tolist(),
        "any": distributed.any_process(rank == 1),
        "metrics": distributed.combine_metrics(
            {"episodes": 1.0 + rank, "reward": float(rank), "loss": 2.0}, summed=["episodes"]
        ),
        "gathered": distributed.gather_to_main(rank),
    }
    distributed.destroy_process_group()
    torch.save({"updates": updates, "exchanged": exchanged}, folder / f"rank{rank}.pt")


TWO_GPUS = pytest.mark.skipif(
    torch.cuda.device_count() < WORLD_SIZE, reason=f"needs {WORLD_SIZE} CUDA devices"
)
DEVICES = ["cpu", pytest.param("cuda", marks=[pytest.mark.gpu, TWO_GPUS])]


@pytest.mark.slow
@pytest.mark.parametrize("device", DEVICES)
def test_two_processes_train_alike_checkpoint_and_resume_exactly(tmp_path, device):
    mp.spawn(
        train_resume_and_record,
        args=(free_port(), tmp_path, device),
        nprocs=WORLD_SIZE,
        join=True,
    )
    saved = [torch.load(tmp_path / f"rank{rank}.pt") for rank in range(WORLD_SIZE)]
    ranks = [rank["updates"] for rank in saved]
    assert len(ranks[0]) == len(ranks[1]) == 2 * (3 + 1 + 2)
    for index, (first, second) in enumerate(zip(*ranks, strict=True)):
        what = "learning rates" if index % 2 else "parameters and return statistics"
        assert torch.equal(first, second), f"the ranks' {what} differ after update {index // 2}"
    assert not torch.equal(ranks[0][0], ranks[0][2])  # they do learn
    assert not torch.equal(ranks[0][1], ranks[0][3])  # the adaptive rate moves
    first, second = (rank["exchanged"] for rank in saved)
    assert first["average"] == second["average"] == [0.5, 0.5]
    assert first["any"] and second["any"]
    assert first["metrics"] == second["metrics"] == {"episodes": 3.0, "reward": 0.5, "loss": 2.0}
    assert first["gathered"] == [0, 1] and second["gathered"] is None

    a, c = (load_checkpoint(tmp_path / name / "checkpoints/last.pt") for name in ("a", "c"))
    assert a["env_steps"] == c["env_steps"] == 3 * WORLD_SIZE * FRAMES
    assert a["world_size"] == c["world_size"] == WORLD_SIZE
    # a killed-and-resumed run continues exactly: the weights, and each rank's environments
    for name, value in a["networks"].items():
        torch.testing.assert_close(c["networks"][name], value, atol=0, rtol=0)
    torch.testing.assert_close(c["simulator"], a["simulator"], atol=0, rtol=0)
    (rank1_a,), (rank1_c,) = a["rank_states"], c["rank_states"]
    torch.testing.assert_close(rank1_c["simulator"], rank1_a["simulator"], atol=0, rtol=0)
    torch.testing.assert_close(rank1_c["torch_rng"], rank1_a["torch_rng"], atol=0, rtol=0)
    # each rank has environments of its own (seed run.seed + rank)
    simulators = a["simulator"], rank1_a["simulator"]
    assert any(not torch.equal(simulators[0][key], simulators[1][key]) for key in simulators[0])


def minibatches_of_one_iteration(trainer: OnPolicyTrainer) -> dict:
    """The sizes of the mini-batches that one iteration's loss runs on (in sequences), and the
    optimiser steps it takes (AdamW's step count)."""
    sizes = []
    trainer.loss.register_forward_pre_hook(lambda _, inputs: sizes.append(inputs[0].shape[0]))
    trainer.train_iteration()
    (steps,) = {int(state["step"]) for state in trainer.optimizer.state.values()}
    return {"sizes": sizes, "steps": steps, "minibatches": trainer.minibatches}


def split_into_minibatches(rank: int, port: int, folder: Path) -> None:
    """One of two gloo ranks: one iteration of 8 environments with ``train.minibatches=2``,
    then the trainer of ``train.minibatches=5``, which two processes cannot split 8 into."""
    join(rank, port, "cpu")
    counted = minibatches_of_one_iteration(eight_environments("mapoca", "cpu", minibatches=2))
    try:
        eight_environments("mapoca", "cpu", minibatches=5)
    except ValueError as error:
        counted["refusal"] = str(error)
    distributed.destroy_process_group()
    torch.save(counted, folder / f"rank{rank}.pt")


def test_each_rank_splits_its_batch_so_that_a_step_averages_one_process_mini_batch(tmp_path):
    single = minibatches_of_one_iteration(eight_environments("mapoca", "cpu", minibatches=2))
    # 2 epochs x 2 mini-batches of 4 of the 8 sequences
    assert single == {"sizes": [4] * 4, "steps": 4, "minibatches": 2}
    mp.spawn(split_into_minibatches, args=(free_port(), tmp_path), nprocs=WORLD_SIZE, join=True)
    for rank in range(WORLD_SIZE):
        counted = torch.load(tmp_path / f"rank{rank}.pt")
        # twice the mini-batches, each half the size: a step of both ranks averages 4 sequences
        assert counted.pop("refusal") == (
            "train.minibatches (5) x 2 processes exceeds train.num_envs (8): a mini-batch holds "
            "whole environment sequences, so use fewer mini-batches or processes or more "
            "environments"
        )
        assert counted == {"sizes": [2] * 8, "steps": 2 * single["steps"], "minibatches": 4}


def torchrun(script: Path, folder: Path, *overrides: str) -> subprocess.CompletedProcess:
    """``script`` (a recipe) under torchrun with two processes and the smoke config, in
    ``folder``."""
    command = [sys.executable, "-m", "torch.distributed.run", "--standalone"]
    return subprocess.run(
        [*command, f"--nproc_per_node={WORLD_SIZE}", str(script)]
        + ["--config-name", "smoke", *overrides],
        cwd=folder,
        capture_output=True,
        text=True,
        timeout=300,
        env={**os.environ, "OMP_NUM_THREADS": "1"},
    )


@pytest.mark.slow
@pytest.mark.parametrize("device", DEVICES)
def test_the_recipes_under_torchrun_write_from_rank_zero_alone(tmp_path, device):
    recipes = ROOT / "recipes"

    def torchrun_recipe(script: str, *overrides: str) -> subprocess.CompletedProcess:
        return torchrun(recipes / script, tmp_path, f"run.device={device}", *overrides)

    pretrain = torchrun_recipe("mapoca_pretrain.py", "run.total_env_steps=64", "run.eval_every=1")
    assert pretrain.returncode == 0, pretrain.stderr
    # one Hydra folder (rank 0's), one line of summary
    (run_dir,) = [path.parent for path in tmp_path.glob("outputs/*/*/config.yaml")]
    assert pretrain.stdout.count("env-steps in 1 iterations") == 1
    # the smoke config's 2 mini-batches of 4 environments: 4 of 1 on each rank
    assert pretrain.stdout.count("each splitting its batch into 4 mini-batches per epoch") == 1
    last = load_checkpoint(run_dir / "checkpoints/last.pt")
    assert last["env_steps"] == 64 and last["world_size"] == WORLD_SIZE

    finetune = torchrun_recipe(
        "mapoca_finetune.py",
        f"run.pretrained={run_dir}/checkpoints/last.pt",
        "env.grid_size=10",
        "env.num_agents=6",
        "run.total_env_steps=64",
        "hydra.run.dir=finetune",
    )
    assert finetune.returncode == 0, finetune.stderr
    tuned = load_checkpoint(tmp_path / "finetune/checkpoints/last.pt")
    assert tuned["env_config"]["num_agents"] == 6 and tuned["iteration"] == 1

    # resumed by one process: rank 0's environments continue, rank 1's are left behind
    single = subprocess.run(
        [sys.executable, str(ROOT / "recipes" / "mapoca_pretrain.py"), "--config-name", "smoke"]
        + [f"run.resume={run_dir}/checkpoints/last.pt", "run.total_env_steps=96"]
        + [f"run.device={device}"]
        + ["hydra.run.dir=single"],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert single.returncode == 0, single.stderr
    assert "trained by 2 process(es) and continues with 1" in single.stdout
    assert load_checkpoint(tmp_path / "single/checkpoints/last.pt")["env_steps"] == 96


@pytest.mark.slow
def test_a_curriculum_under_torchrun_advances_every_process_to_the_next_stages_padding(tmp_path):
    curriculum = (
        "curriculum=auto",
        "curriculum.stages=3",
        "curriculum.start_grid_size=6",
        "curriculum.start_num_agents=2",
        "curriculum.start_num_objects=1",
        "curriculum.threshold=0",  # rank 0's first evaluation advances both
        "curriculum.eval_every=2",
    )
    script = ROOT / "recipes" / "mapoca_pretrain.py"
    result = torchrun(script, tmp_path, *curriculum, "run.total_env_steps=192", "hydra.run.dir=a")
    assert result.returncode == 0, result.stderr
    assert result.stdout.count("stage 2/3: 7x7 columns, 3 agents, 2 spheres from 128") == 1
    last = load_checkpoint(tmp_path / "a/checkpoints/last.pt")
    assert last["curriculum"]["stage"] == 1 and last["iteration"] == 3
    # both ranks collected the second stage's batch, padded to its 3 agents, not the target's 4
    for carry in (last["carry"], last["rank_states"][0]["carry"]):
        assert carry["agents", "mask"].shape[-1] == 3


STOPS_ANSWERING = """
import sys, time
import torch
from terrashift_rl.training import distributed
timeout = float(sys.argv[1])
distributed.init_process_group(
    "cpu", key="run.device", timeout=timeout, timeout_key="run.collective_timeout_s"
)
if distributed.rank() == 1:
    time.sleep(10 * timeout)  # alive, but it never reaches the exchange
with distributed.watch("the test's exchange", iteration=7):
    distributed.average(torch.ones(1))
"""


def test_a_rank_that_stops_answering_ends_the_run_within_the_timeout(tmp_path):
    timeout = 2
    environment = {
        **os.environ,
        "MASTER_ADDR": "127.0.0.1",
        "MASTER_PORT": str(free_port()),
        "WORLD_SIZE": str(WORLD_SIZE),
        "OMP_NUM_THREADS": "1",
    }
    ranks = [
        subprocess.Popen(
            [sys.executable, "-c", STOPS_ANSWERING, str(timeout)],
            env={**environment, "RANK": str(rank), "LOCAL_RANK": str(rank)},
            stderr=subprocess.PIPE,
            text=True,
        )
        for rank in range(WORLD_SIZE)
    ]
    try:
        _, stderr = ranks[0].communicate(timeout=120)
    finally:
        ranks[1].kill()
        ranks[1].wait()
    assert ranks[0].returncode == distributed.WATCHDOG_EXIT_CODE, stderr
    message = re.search(
        r"rank 0: the test's exchange in iteration 7 has waited (\d+) s "
        r"for the other ranks, longer than run.collective_timeout_s=2: another rank stopped "
        r"answering or died",
        stderr,
    )
    assert message, stderr
    # checked a few times per timeout; well before the process group's own, 30 s later
    assert timeout <= int(message[1]) <= timeout + 2
    assert "in average" in stderr  # the stack of the waiting thread follows


DIES_IN_ITS_THIRD_ITERATION = """
import os, runpy, sys
from terrashift_rl.training import OnPolicyTrainer

train_iteration = OnPolicyTrainer.train_iteration


def dies_in_the_third(trainer):
    if os.environ["RANK"] == "1" and trainer.iteration == 2:
        os._exit(9)
    return train_iteration(trainer)


OnPolicyTrainer.train_iteration = dies_in_the_third
sys.argv[0] = {recipe!r}
runpy.run_path(sys.argv[0], run_name="__main__")
"""


@pytest.mark.slow
def test_a_rank_that_dies_ends_the_run_and_leaves_the_last_checkpoint_whole(tmp_path):
    script = tmp_path / "dies.py"
    recipe = ROOT / "recipes" / "mapoca_pretrain.py"
    script.write_text(DIES_IN_ITS_THIRD_ITERATION.format(recipe=str(recipe)))
    start = time.monotonic()
    run = torchrun(
        script,
        tmp_path,
        f"run.total_env_steps={10 * WORLD_SIZE * FRAMES}",
        "run.checkpoint_every=1",
        "run.eval_every=null",
        "run.collective_timeout_s=10",
        "hydra.run.dir=run",
    )
    assert run.returncode != 0
    # torchrun names the rank that failed first, and its exit status
    assert re.search(r"rank\s*: 1 \(local_rank: 1\)\s+exitcode\s*: 9", run.stderr), run.stderr
    assert time.monotonic() - start < 240
    last = load_checkpoint(tmp_path / "run/checkpoints/last.pt")
    assert last["env_steps"] == 2 * WORLD_SIZE * FRAMES and last["world_size"] == WORLD_SIZE


def test_without_a_process_group_the_helpers_change_nothing():
    assert not distributed.is_distributed()
    assert (distributed.world_size(), distributed.rank()) == (1, 0)
    assert distributed.is_main_process()
    value = torch.arange(3.0)
    assert distributed.average(value) is value
    assert distributed.any_process(True) and not distributed.any_process(False)
    assert distributed.gather_to_main({"x": value}) == [{"x": value}]
    metrics = {"episodes": 2.0, "loss_critic": 0.5}
    assert distributed.combine_metrics(metrics, summed=["episodes"]) is metrics
    state = {"simulator": 1, "carry": 2, "optimizer": 3}
    assert distributed.rank_entries(state, ["simulator", "carry"]) == {"simulator": 1, "carry": 2}


def test_under_torchrun_a_gpu_index_or_more_processes_than_gpus_are_refused(monkeypatch):
    monkeypatch.setenv("WORLD_SIZE", "4")
    monkeypatch.setenv("LOCAL_WORLD_SIZE", "4")
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 2)
    with pytest.raises(ValueError, match="run.device='cuda:1', but under torchrun run.device"):
        distributed.init_process_group("cuda:1", key="run.device")
    message = (
        "torchrun started 4 processes on this host, which has 2 CUDA device.s.: one process "
        "per GPU, so use --nproc_per_node=2 or fewer"
    )
    with pytest.raises(ValueError, match=message):
        distributed.init_process_group("cuda", key="run.device")
