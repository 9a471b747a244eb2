"""kl_response.py: the recipes' network sizes with either distribution, and one row per setting."""

import json
import math
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parents[2] / "benchmarks"))

import kl_response  # noqa: E402


def test_model_config_is_the_recipes_network_with_the_distribution():
    config = kl_response.model_config("medium", "normal")
    assert (config.embed_dim, config.trunk_layers, config.distribution) == (64, 2, "normal")


def test_every_distribution_and_rate_gets_a_measured_row(tmp_path, monkeypatch):
    output = tmp_path / "kl.json"
    argv = ["kl_response.py", "--model", "small", "--num-envs", "8", "--iterations", "1"]
    argv += ["--lrs", "3e-4", "3e-3", "--output", str(output)]
    monkeypatch.setattr(sys, "argv", argv)
    kl_response.main()
    rows = json.loads(output.read_text())["rows"]
    settings = [(row["distribution"], row["lr"]) for row in rows]
    assert settings == [("beta", 3e-4), ("beta", 3e-3), ("normal", 3e-4), ("normal", 3e-3)]
    for row in rows:
        assert math.isfinite(row["kl_approx"]) and row["kl_approx"] > 0
        assert 0 <= row["clip_fraction"] <= 1
    # from the same weights and data, ten times the rate moves each policy further
    kl = {(row["distribution"], row["lr"]): row["kl_approx"] for row in rows}
    assert kl["beta", 3e-3] > kl["beta", 3e-4] and kl["normal", 3e-3] > kl["normal", 3e-4]
