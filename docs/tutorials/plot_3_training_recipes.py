"""
Training, resuming, finetuning and evaluating
=============================================

The recipes in ``recipes/`` are Hydra scripts: pretraining, finetuning and evaluation. This
tutorial runs each of them on the CPU with the ``smoke`` config (an 8 x 8 grid, 4 agents,
2 spheres, the ``small`` network, 4 environments), exactly as you would from a shell; the
:doc:`/training` guide lists the settings and what a real run on a GPU looks like.
"""

import json
import subprocess
import sys
import tempfile
from pathlib import Path

import matplotlib.pyplot as plt
import torch
from PIL import Image

import terrashift_rl
from terrashift_rl.training import load_checkpoint

# The recipes sit beside the package in the repository (an editable install).
RECIPES = Path(terrashift_rl.__path__[0]).resolve().parent / "recipes"
work = Path(tempfile.mkdtemp(prefix="terrashift_tutorial_"))


def recipe(script: str, *overrides: str) -> str:
    """Runs ``python recipes/<script> <overrides>`` and returns its last output line."""
    command = [sys.executable, str(RECIPES / script), *overrides]
    print("$ python recipes/" + " ".join([script, *overrides]).replace(str(work), "<tmp>"))
    done = subprocess.run(command, capture_output=True, text=True, check=True)
    return done.stdout.strip().splitlines()[-1].replace(str(work), "<tmp>")


# %%
# Pretraining
# -----------
# ``--config-name smoke`` selects ``recipes/configs/smoke.yaml``; every other setting is a
# Hydra override (``group=option`` picks a config file of a group, ``group.field=value`` sets one
# field). ``hydra.run.dir`` chooses the run directory, by default ``outputs/<date>/<time>/``.
# Here the CSV logger replaces the smoke config's ``logger=none``.

run = work / "pretrain"
print(
    recipe(
        "mapoca_pretrain.py",
        "--config-name",
        "smoke",
        "logger=csv",
        "run.total_env_steps=256",
        f"hydra.run.dir={run}",
    )
)

# %%
# The run directory holds the resolved config, the logs and the checkpoint ``last.pt``,
# written every ``run.checkpoint_every`` iterations, at the end, and on Ctrl-C or SIGTERM, and
# ``best.pt``: the networks at the best mean reward per decision over ``run.best_window``
# iterations, for evaluation or finetuning.

for path in sorted(run.rglob("*")):
    if path.is_file() and "scalars" not in path.parts:
        print(path.relative_to(run))

# %%
# Logs
# ----
# With ``logger=csv`` every metric is a file ``logs/<run name>/scalars/<metric>.csv`` of
# ``step,value`` lines, the step counting environment steps.

scalars = next(run.glob("logs/*/scalars"))
print(sorted(path.stem for path in scalars.glob("*.csv")))


def read_scalar(name: str) -> tuple[list[float], list[float]]:
    steps, values = [], []
    for line in (scalars / f"{name}.csv").read_text().split():
        step, value = line.split(",")
        steps.append(float(step))
        values.append(float(value))
    return steps, values


# %%
# Checkpoints and resume
# ----------------------
# A checkpoint is a ``dict`` saved with ``torch.save`` (atomically: a crash never leaves a
# partial file): the network, optimiser and schedule state, the counters, the configs, and the
# logger's run id, so a resumed wandb run continues the same curves.

checkpoint = load_checkpoint(run / "checkpoints" / "last.pt")
print({key: type(value).__name__ for key, value in checkpoint.items()})
print("env steps so far:", checkpoint["env_steps"])

# %%
# ``run.resume`` continues a killed or finished run exactly where it stopped; raise
# ``run.total_env_steps`` (or give ``run.minutes``) to train further. The scene, network and
# batch size must match the checkpoint's, and the recipe says which does not.

resumed = work / "resumed"
print(
    recipe(
        "mapoca_pretrain.py",
        "--config-name",
        "smoke",
        "logger=csv",
        "run.total_env_steps=512",
        f"run.resume={run / 'checkpoints' / 'last.pt'}",
        f"hydra.run.dir={resumed}",
    )
)

# %%
# Finetuning
# ----------
# ``mapoca_finetune.py`` starts from a pretraining checkpoint's weights (``run.pretrained``)
# with a fresh optimiser and schedules, on the 30 x 30 grid with 16 agents by default. The
# networks are size-agnostic, so the same weights run a larger scene; here a 10 x 10 grid with
# 6 agents keeps it quick, and the network config must stay the checkpoint's (``model=small``).

finetuned = work / "finetune"
print(
    recipe(
        "mapoca_finetune.py",
        "env=smoke",
        "env.grid_size=10",
        "env.num_agents=6",
        "model=small",
        "train=smoke",
        "train.num_envs=4",
        "logger=none",
        "run.device=cpu",
        "run.total_env_steps=64",
        f"run.pretrained={resumed / 'checkpoints' / 'last.pt'}",
        f"hydra.run.dir={finetuned}",
    )
)

# %%
# Evaluation and videos
# ---------------------
# ``evaluate.py`` plays the policy in evaluation mode (``respawn=False``: an episode ends once
# every sphere is resolved or at the step limit), beside the random, zero-action and scripted
# baselines, writes ``evaluation.json`` and records a video (``video.format=mp4`` or ``gif``;
# ``video.steps=0`` turns it off). It evaluates on the checkpoint's scene.

evaluation = work / "evaluate"
print(
    recipe(
        "evaluate.py",
        f"checkpoint={resumed / 'checkpoints' / 'last.pt'}",
        "episodes=4",
        "device=cpu",
        "video.steps=8",
        "video.every=4",
        "video.format=gif",
        f"hydra.run.dir={evaluation}",
    )
)
results = json.loads((evaluation / "evaluation.json").read_text())
scores = {
    "policy (Beta mean)": results["deterministic"],
    "policy (sampled)": results["stochastic"],
    **results["baselines"],
}
for name, metrics in scores.items():
    print(
        f"{name:20s} success {metrics['success_rate']:.2f}  "
        f"reward/decision {metrics['mean_reward_per_decision']:+.4f}"
    )

# %%
# A few seconds of training do not teach anything yet; :doc:`/results` shows real runs. The
# reward curves of both pretraining runs and the last frame of the video:

fig, (curve, video) = plt.subplots(1, 2, figsize=(11, 3.8), width_ratios=[1, 1.6])
for name, run_dir in (("pretrain", run), ("resumed", resumed)):
    scalars = next(run_dir.glob("logs/*/scalars"))
    reward_file = next(p.stem for p in scalars.glob("*.csv") if "reward" in p.stem)
    curve.plot(*read_scalar(reward_file), marker="o", label=name)
curve.set_xlabel("env steps")
curve.set_ylabel(reward_file)
curve.legend()
gif = Image.open(evaluation / "rollout.gif")
gif.seek(gif.n_frames - 1)
video.imshow(gif.convert("RGB"))
video.set_axis_off()
fig.tight_layout()
plt.show()

# %%
# The same loop in Python
# -----------------------
# The recipes compose :mod:`terrashift_rl.training`: the settings room
# (``RecipeConfig``), ``make_training_env``, ``make_terrashift_networks`` and
# ``make_trainer``, put together in ``train()`` of ``recipes/mapoca_pretrain.py``; read it
# top to bottom to see how. ``torch``
# picks the CPU here: a GPU run only changes ``run.device``.
print("CUDA available:", torch.cuda.is_available())
