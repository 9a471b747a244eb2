"""loss_speed.py: one measured row per method, with the parts of an update."""

import argparse
import math
import sys
from pathlib import Path

import pytest
import torch

sys.path.insert(0, str(Path(__file__).parents[2] / "benchmarks"))

import loss_speed  # noqa: E402


def tiny_args(**overrides) -> argparse.Namespace:
    settings = {"device": "cpu", "envs": 2, "steps": 3, "minibatch": 3, "repeats": 1}
    settings |= {"threads": 1, "parts": True, "mlp_width": 8} | overrides
    return argparse.Namespace(**settings)


MLP_METHODS = (
    "MAPOCA, MLP value",
    "MAPOCA, MLP critics",
    "MAPOCA, MLP critics, least-variance weight",
)


@pytest.mark.parametrize("method", (*loss_speed.DEFAULT_METHODS, *MLP_METHODS))
def test_each_method_gets_a_measured_row_with_its_parts(method):
    row = loss_speed.timing(method, 3, tiny_args())
    assert (row["method"], row["agents"]) == (method, 3)
    assert row["update_s"] > 0 and row["update_processor_s"] > 0
    assert math.isfinite(loss_speed.peak_memory(method, 3, tiny_args()))
    critics = ("value network", "baseline network") if "MAPOCA" in method else ("critic",)
    for part in ("step", "actor", "optimiser", "loss terms", "estimation", *critics):
        assert math.isfinite(row["parts_ms"][part])


def test_the_least_variance_method_is_the_mlp_critics_with_the_weight_lowered():
    plain = loss_speed.make_loss("MAPOCA, MLP critics", 3, tiny_args())
    lowered = loss_speed.make_loss("MAPOCA, MLP critics, least-variance weight", 3, tiny_args())
    assert lowered.least_variance_weight and not plain.least_variance_weight
    assert type(lowered.baseline_network) is type(plain.baseline_network)


def test_an_update_trains_every_network_of_the_loss():
    torch.manual_seed(0)
    args = tiny_args()
    loss = loss_speed.make_loss("MAPOCA", 3, args)
    before = [parameter.clone() for parameter in loss.parameters()]
    batch = loss_speed.make_batch(args.envs, args.steps, 3, torch.device("cpu"))
    with torch.no_grad():
        loss.actor_network(batch)
    optimiser = torch.optim.Adam(loss.parameters(), lr=1e-2)
    loss_speed.update(loss, optimiser, batch, args.minibatch)
    moved = [not torch.equal(old, new) for old, new in zip(before, loss.parameters(), strict=True)]
    assert all(moved)
