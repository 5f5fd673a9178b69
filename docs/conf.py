"""Sphinx configuration of the sb3-pevfa documentation (Markdown pages through MyST, API pages through autodoc).

Build (warnings are errors, as in CI):  python -m sphinx -W --keep-going -b html docs docs/_build/html
"""

import pathlib
import sys

ROOT = pathlib.Path(__file__).parents[1]
sys.path.insert(0, str(ROOT))

project = "sb3-pevfa"
author = "sb3-pevfa contributors"
copyright = "2026, sb3-pevfa contributors"
release = (ROOT / "sb3_pevfa" / "version.txt").read_text().strip()
version = release

extensions = ["myst_parser", "sphinx.ext.autodoc", "sphinx.ext.viewcode", "sphinx.ext.mathjax"]
source_suffix = {".md": "markdown"}
root_doc = "index"
exclude_patterns = ["_build", "results/**"]
myst_enable_extensions = ["dollarmath", "colon_fence"]
myst_heading_anchors = 3

autodoc_member_order = "bysource"
autodoc_default_options = {"members": True, "show-inheritance": True}
autodoc_typehints = "description"
autodoc_mock_imports: list[str] = []

html_theme = "sphinx_rtd_theme"
html_title = f"sb3-pevfa {release}"
html_static_path: list[str] = []
