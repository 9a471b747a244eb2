"""The tracked tree stays small enough to carry, and the docs name only what it holds."""

import glob
import re
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).parents[1]
LIMIT_BYTES = 1_000_000
TREE_LIMIT_BYTES = 4 * 2**20
RESULTS_PAGE_LINES = 300
README_FIRST_SCREEN = 15
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
# a figure (docs/figures/, or figures/ from a page in docs/), a results file, or a run summary
# named through results.md's shell variable T=benchmarks/results/training
REFERENCE = re.compile(
    r"(?P<path>(?:docs/)?figures/[\w.-]+\.(?:png|gif)|benchmarks/results/[\w./?-]+\.json)"
    r"|\$T/(?P<summary>[\w.?-]+\.json)"
)
SCRIPT = re.compile(r"benchmarks/[\w]+\.py")


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


def test_the_tracked_tree_stays_under_4_mib():
    total = sum(path.stat().st_size for path in tracked_files() if path.is_file())
    assert total < TREE_LIMIT_BYTES, (
        f"the tracked tree holds {total / 2**20:.2f} MiB, the limit is 4 MiB: keep in git only "
        "the run summaries and figures that docs/results.md draws on"
    )


def test_the_results_page_stays_a_page():
    lines = (ROOT / "docs" / "results.md").read_text().count("\n")
    assert lines <= RESULTS_PAGE_LINES, (
        f"docs/results.md has {lines} lines (at most {RESULTS_PAGE_LINES}): history belongs in "
        "docs/experiments.md, one line per finding"
    )


def referenced_files(page: Path) -> list[str]:
    names = []
    for match in REFERENCE.finditer(page.read_text()):
        if match["summary"]:
            names.append(f"benchmarks/results/training/{match['summary']}")
        elif match["path"].startswith("figures/"):
            names.append(f"docs/{match['path']}")
        else:
            names.append(match["path"])
    return names


@pytest.mark.parametrize("page", PAGES, ids=lambda page: page.name)
def test_every_figure_and_results_file_a_page_names_exists(page):
    missing = [name for name in referenced_files(page) if not glob.glob(str(ROOT / name))]
    assert not missing, f"{page.name} names files the tree does not hold: {missing}"


@pytest.mark.parametrize(
    "page", [p for p in PAGES if p.name != "experiments.md"], ids=lambda page: page.name
)
def test_every_benchmark_script_a_page_names_exists(page):
    # docs/experiments.md is the log: it names retired scripts, which git history keeps
    missing = sorted({s for s in SCRIPT.findall(page.read_text()) if not (ROOT / s).is_file()})
    assert not missing, f"{page.name} names scripts the tree does not hold: {missing}"


def test_the_readme_opens_with_the_project_its_commands_and_a_picture():
    first_screen = (ROOT / "README.md").read_text().splitlines()[:README_FIRST_SCREEN]
    text = "\n".join(first_screen)
    assert first_screen[0] == "# terrashift_rl"
    assert "**TerraShift** is" in text
    commands = [line for line in first_screen if line.startswith("python3 -m venv")]
    assert [command.rsplit("&& ", 1)[-1] for command in commands] == [
        "python recipes/mapoca_pretrain.py",
        "pytest",
    ], "the README's first commands are the main job and the tests (.ci/run runs the second)"
    pictures = re.findall(r'src="(docs/figures/[\w.-]+)"', text)
    assert pictures and all((ROOT / picture).is_file() for picture in pictures)
    assert first_screen[-1].startswith("|"), "the headline table ends the first screen"
