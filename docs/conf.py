"""Sphinx configuration of the pocoloco site (``bash scripts/docs.sh`` builds it into docs/_build/html)."""

from __future__ import annotations

import pocoloco

project = "pocoloco"
author = "the pocoloco developers"
copyright = "2026, the pocoloco developers"  # noqa: A001 - Sphinx's name
release = pocoloco.__version__
version = release

extensions = [
    "myst_parser",  # Markdown pages
    "sphinx.ext.autodoc",  # the API reference, from the docstrings
    "sphinx.ext.napoleon",  # Google-style "Args:" / "Returns:" sections
    "sphinx.ext.viewcode",
    "sphinxarg.ext",  # the CLI reference, from the real argparse parser
]
source_suffix = {".md": "markdown", ".rst": "restructuredtext"}
exclude_patterns = ["_build"]
root_doc = "index"

myst_enable_extensions = ["colon_fence", "deflist"]
myst_heading_anchors = 4  # "page.md#a-heading" links
suppress_warnings = ["myst.header"]  # moved notebook pages start at a level-2 heading

autodoc_member_order = "bysource"
autodoc_typehints = "description"
autodoc_default_options = {"members": True, "show-inheritance": False}
napoleon_google_docstring = True
napoleon_numpy_docstring = False
nitpicky = False

html_theme = "furo"
html_title = f"pocoloco {release}"
html_static_path: list[str] = []
html_theme_options = {"sidebar_hide_name": False}
