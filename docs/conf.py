"""Sphinx configuration of sb3-soup's documentation (`make doc`), in the shape of Stable-Baselines3's: the pages are
Markdown (MyST), the API page is autodoc of the package's public names, whose docstrings are Sphinx ``:param:`` style."""

import os
import sys

# The checkout's package first (the docs describe the code next to them, installed or not)
sys.path.insert(0, os.path.abspath(".."))
# Nothing here renders: no display for matplotlib, no GL context for MuJoCo if anything imported it
os.environ.setdefault("MPLBACKEND", "Agg")
os.environ.setdefault("MUJOCO_GL", "egl")
# The RL Zoo import hook has nothing to do while the docs are built
os.environ.setdefault("SB3_SOUP_ZOO_HOOK", "0")

with open(os.path.join(os.path.dirname(__file__), "..", "sb3_soup", "version.txt")) as file_handler:
    release = file_handler.read().strip()
version = release

project = "sb3-soup"
author = "sb3-soup contributors"
copyright = "2026, sb3-soup contributors"

extensions = [
    "sphinx.ext.autodoc",
    "sphinx.ext.viewcode",
    "myst_parser",
]

source_suffix = {".rst": "restructuredtext", ".md": "markdown"}
root_doc = "index"
exclude_patterns = ["_build", "Thumbs.db", ".DS_Store"]

# Markdown: "#section-title" links between pages resolve to the headings' anchors (GitHub's slugs), down to ####
myst_heading_anchors = 4
myst_enable_extensions = ["dollarmath"]

# autodoc: the public API as the package exports it, members in the order of the source
autodoc_member_order = "bysource"
autodoc_typehints = "signature"
autodoc_default_options = {"show-inheritance": True}

html_theme = "sphinx_rtd_theme"
html_title = f"sb3-soup {release}"
html_static_path: list[str] = []
# the sidebar shows the pages, not the report files of docs/results/ (a hidden toctree in index.md)
html_theme_options = {"includehidden": False}


def _readme_is_the_front_page(app, docname, source):
    """The pages link to the README as GitHub shows them (``../README.md#can-i-use``); in the built documentation the
    README is the front page (``index.md`` includes it), so those links point there."""
    source[0] = source[0].replace("](../README.md", "](index.md")


def setup(app):
    app.connect("source-read", _readme_is_the_front_page)
