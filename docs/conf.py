"""Sphinx configuration of the terrashift_rl documentation.

Build (from the repository root, warnings as errors, as CI does)::

    sphinx-build -W --keep-going -b html docs docs/_build/html
"""

from __future__ import annotations

import os
import re
import sys
from pathlib import Path

import matplotlib

matplotlib.use("Agg")  # tutorials draw headless
os.environ.setdefault("WANDB_MODE", "disabled")

DOCS = Path(__file__).resolve().parent
# The repository root first, so autodoc documents this checkout's package.
sys.path[:0] = [str(DOCS.parent), str(DOCS / "_ext")]

import terrashift_rl  # noqa: E402

project = "terrashift_rl"
author = "the terrashift_rl developers"
copyright = "2026, the terrashift_rl developers"  # noqa: A001
release = terrashift_rl.__version__
version = release

extensions = [
    "sphinx.ext.autodoc",
    "sphinx.ext.napoleon",
    "sphinx.ext.mathjax",
    "sphinx.ext.viewcode",
    "myst_parser",
    "sphinx_gallery.gen_gallery",
    "config_reference",
]

source_suffix = {".rst": "restructuredtext", ".md": "markdown"}
root_doc = "index"
exclude_patterns = [
    "_build",
    "auto_tutorials/*.ipynb",
    "auto_tutorials/*.py",
    "auto_tutorials/*.zip",
    "auto_tutorials/*.json",
]

# --- MyST: the Markdown pages under docs/ are included as they are -----------------------------
myst_enable_extensions = ["dollarmath", "colon_fence"]
myst_heading_anchors = 3

# --- autodoc / napoleon: Google-style docstrings ------------------------------------------------
autodoc_default_options = {"members": True, "show-inheritance": True}
autodoc_member_order = "bysource"
autodoc_typehints = "description"
autodoc_class_signature = "separated"
napoleon_google_docstring = True
napoleon_numpy_docstring = False
napoleon_use_rtype = False

# --- sphinx-gallery: every tutorial is a script executed during the build ----------------------
sphinx_gallery_conf = {
    "examples_dirs": ["tutorials"],
    "gallery_dirs": ["auto_tutorials"],
    "filename_pattern": r"/plot_",
    "within_subsection_order": "FileNameSortKey",
    "download_all_examples": False,
    "remove_config_comments": True,
    "abort_on_example_error": True,
    "write_computation_times": False,
    "show_memory": False,
    "image_scrapers": ("matplotlib",),
    # Tutorials whose script is unchanged are skipped unless this is set (CI's test sets it), so
    # a change in the package still re-runs them there.
    "run_stale_examples": os.environ.get("TERRASHIFT_DOCS_RERUN") == "1",
}

# --- HTML ---------------------------------------------------------------------------------------
html_theme = "furo"
html_title = f"terrashift_rl {release}"


# --- docstrings: the package writes shapes as [*B, K, d] and norms as |x| in plain text ---------
_LITERAL = re.compile(r"(``.+?``)")
_PLAIN_TEXT_FIXES = (
    (re.compile(r"\[\*"), r"[\\*"),  # [*B, ...]: a shape, not the start of emphasis
    (re.compile(r"(\w)_(?=[-\s,.;:)])"), r"\1\\_"),  # a_-i: a subscript, not a link
    (re.compile(r"\|(\w+)\|"), r"\\|\1\\|"),  # |x|: an absolute value, not a substitution
)


def _escape_plain_text(app, what, name, obj, options, lines):
    """Escapes the plain-text notations above outside inline literals, in place."""
    for index, line in enumerate(lines):
        parts = _LITERAL.split(line)
        for part_index in range(0, len(parts), 2):
            for pattern, replacement in _PLAIN_TEXT_FIXES:
                parts[part_index] = pattern.sub(replacement, parts[part_index])
        lines[index] = "".join(parts)


def setup(app):
    app.connect("autodoc-process-docstring", _escape_plain_text)
