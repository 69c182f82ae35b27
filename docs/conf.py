"""Sphinx configuration: the docs site, Markdown (MyST) pages and the API from the docstrings.

Build it with ``python -m sphinx -W --keep-going -b html docs OUTDIR`` (tools/test does, into a
temporary directory): a warning fails the build, so a broken link or docstring shows at once.
"""
from __future__ import annotations

import rocoma_can

project = "rocoma-can"
author = "rocoma-can contributors"
release = version = rocoma_can.__version__

extensions = [
    "myst_parser",
    "sphinx.ext.autodoc",
]
source_suffix = {".md": "markdown"}
root_doc = "index"
exclude_patterns = ["_build"]

# page.md#a-heading links, as GitHub makes them, work in the built site too
myst_heading_anchors = 3

# the docstrings are reST; members in source order, as each module tells its story
autodoc_member_order = "bysource"
autodoc_typehints = "description"

html_theme = "alabaster"
html_title = f"rocoma-can {release}"
