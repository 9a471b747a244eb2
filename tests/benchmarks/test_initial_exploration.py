"""initial_exploration.py: random actions from the policy head's initial Beta."""

import dataclasses
import json
import subprocess
import sys
from pathlib import Path

import torch
from tensordict import TensorDict

from terrashift_rl.modules.config import TerraShiftModelConfig

BENCHMARKS = Path(__file__).parents[2] / "benchmarks"
sys.path.insert(0, str(BENCHMARKS))

from initial_exploration import InitialBetaPolicy  # noqa: E402


def test_the_sampled_actions_have_the_initial_mean_inside_the_range():
    config = dataclasses.replace(
        TerraShiftModelConfig.small(), initial_action_mean=[0.0, 0.0, 0.0, -0.5, 0.3, 0.0]
    )
    td = TensorDict({("agents", "observation"): torch.zeros(4096, 8, 9)}, batch_size=[4096])
    torch.manual_seed(0)
    action = InitialBetaPolicy(config, action_dim=6)(td)["agents", "action"]
    assert action.shape == (4096, 8, 6) and bool((action.abs() <= 1.0).all())
    torch.testing.assert_close(
        action.mean(dim=(0, 1)), torch.tensor([0.0, 0.0, 0.0, -0.5, 0.3, 0.0]), atol=0.01, rtol=0
    )


def test_the_script_scores_each_mean_on_the_family_and_refuses_a_bad_mean_before_playing(tmp_path):
    out = tmp_path / "exploration.json"
    command = [sys.executable, str(BENCHMARKS / "initial_exploration.py"), "--device", "cpu"]
    family = ["--actuator", "rotors", "--column-shape", "box", "--num-envs", "2"]
    means = ["--means", "centred", "0,0,0,-0.5,0,0"]
    done = subprocess.run(
        [*command, *family, *means, "--out", str(out)], capture_output=True, text=True
    )
    assert done.returncode == 0, done.stderr
    results = json.loads(out.read_text())
    assert results["scene"].startswith("pretrain, rotors on box columns")
    rows = results["rows"]
    assert [row["initial_action_mean"] for row in rows] == [[], [0.0, 0.0, 0.0, -0.5, 0.0, 0.0]]
    for row in rows:
        assert 0.0 <= row["goal_fraction"] <= 1.0 and row["episodes"] == 2
    refused = subprocess.run(
        [*command, "--means", "centred", "0,0", "--out", str(tmp_path / "refused.json")],
        capture_output=True,
        text=True,
    )
    assert refused.returncode == 2
    assert "--means 0.0,0.0: initial_action_mean needs one value per action dimension" in (
        refused.stderr
    )
    assert not (tmp_path / "refused.json").exists()
