"""plot_camera.py: the figure of camera frames beside the scene and the heightmap."""

import subprocess
import sys
from pathlib import Path

from PIL import Image

SCRIPT = Path(__file__).parents[2] / "benchmarks" / "plot_camera.py"


def test_draws_one_row_per_moment_as_a_palette_png(tmp_path):
    out = tmp_path / "camera.png"
    command = [sys.executable, str(SCRIPT), "--out", str(out), "--camera-resolution", "16"]
    result = subprocess.run(
        [*command, "--steps", "0", "2"], capture_output=True, text=True, timeout=600
    )
    assert result.returncode == 0, result.stderr
    image = Image.open(out)
    assert image.mode == "P"
    assert image.size == (1080, 720)  # 10.8 x 3.6 inches per row at 100 dpi
