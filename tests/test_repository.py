"""The tracked tree stays small enough to carry: no large file outside docs/figures."""

import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).parents[1]
LIMIT_BYTES = 1_000_000


def tracked_files() -> list[Path]:
    try:
        out = subprocess.run(
            ["git", "ls-files", "-z"], cwd=ROOT, capture_output=True, check=True
        ).stdout
    except (OSError, subprocess.CalledProcessError):
        pytest.skip("not a git checkout")
    return [ROOT / name for name in out.decode().split("\0") if name]


def test_no_tracked_file_over_1_mb_outside_docs_figures():
    large = [
        f"{path.relative_to(ROOT)} ({path.stat().st_size / 1e6:.1f} MB)"
        for path in tracked_files()
        if path.is_file()
        and path.stat().st_size > LIMIT_BYTES
        and not path.is_relative_to(ROOT / "docs" / "figures")
    ]
    assert not large, f"keep raw logs and large files out of git: {large}"
