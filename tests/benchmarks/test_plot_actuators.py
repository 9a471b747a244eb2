"""plot_actuators.py: the figure of every actuator family's surface."""

import subprocess
import sys
from pathlib import Path

from PIL import Image

from terrashift_rl.sim import ACTUATORS

SCRIPT = Path(__file__).parents[2] / "benchmarks" / "plot_actuators.py"


def test_draws_one_panel_per_family_as_a_palette_png(tmp_path):
    out = tmp_path / "actuators.png"
    command = [sys.executable, str(SCRIPT), "--out", str(out), "--decisions", "2"]
    result = subprocess.run(command, capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stderr
    image = Image.open(out)
    assert image.mode == "P"
    assert image.size == (round(4.2 * 90) * len(ACTUATORS), 342)  # 4.2 x 3.8 inches a panel
