"""pixel_probe.py: each network is trained and scored on the same frames, and the JSON says so."""

import json
import math
import subprocess
import sys
from pathlib import Path

SCRIPT = Path(__file__).parents[2] / "benchmarks" / "pixel_probe.py"


def test_a_short_probe_scores_every_target_of_each_network(tmp_path):
    out = tmp_path / "probe.json"
    command = [sys.executable, str(SCRIPT), "--out", str(out), "--preset", "small"]
    command += ["--networks", "pixels", "cnn", "--camera-resolution", "16", "--envs", "16"]
    command += ["--snapshots", "2", "--every", "8", "--steps", "3", "--batch", "4"]
    result = subprocess.run(command, capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stderr
    saved = json.loads(out.read_text())
    assert list(saved["networks"]) == ["pixels", "cnn"]
    for scores in saved["networks"].values():
        assert len(scores["r2"]) == len(saved["targets"]) == 6
        # the offsets vary over any frames; in so few the spheres' velocities may not
        assert all(math.isfinite(r2) and r2 <= 1.0 for r2 in scores["r2"][:4])
        assert math.isfinite(scores["train_loss"])
