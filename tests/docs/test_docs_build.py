"""The documentation builds with warnings as errors, running every tutorial on the CPU."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

DOCS = Path(__file__).resolve().parents[2] / "docs"

pytest.importorskip("sphinx", reason="the docs extra is not installed: pip install -e '.[docs]'")
pytest.importorskip("sphinx_gallery")
pytest.importorskip("myst_parser")


@pytest.mark.slow  # about two minutes: every tutorial runs
def test_docs_build_without_warnings(tmp_path: Path) -> None:
    env = {**os.environ, "OMP_NUM_THREADS": "2", "WANDB_MODE": "disabled", "MPLBACKEND": "Agg"}
    env["TERRASHIFT_DOCS_RERUN"] = "1"  # run every tutorial, even where a cached run exists
    command = [sys.executable, "-m", "sphinx", "-W", "--keep-going", "-b", "html", "-q"]
    command += ["-d", str(tmp_path / "doctrees"), str(DOCS), str(tmp_path / "html")]
    build = subprocess.run(command, capture_output=True, text=True, env=env, timeout=900)
    assert build.returncode == 0, (
        f"sphinx-build failed:\n{build.stdout[-5000:]}\n{build.stderr[-10000:]}"
    )
    html = tmp_path / "html"
    pages = ("index", "environment", "physics", "training", "benchmarks", "results", "experiments")
    for page in (*pages, "api"):
        assert (html / f"{page}.html").is_file(), page
    tutorials = sorted((html / "auto_tutorials").glob("plot_*.html"))
    assert len(tutorials) == len(list((DOCS / "tutorials").glob("plot_*.py")))
    reference = (html / "environment.html").read_text()
    assert "contact_stiffness" in reference and "N/m" in reference
    assert (html / "_images" / "shape_actions_h100.png").is_file()
