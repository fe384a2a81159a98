"""Sphinx configuration of the terrainwarp reference: ``make docs`` (warnings are errors)."""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent / "_ext"))

import terrainwarp  # noqa: E402

project = "terrainwarp"
release = version = terrainwarp.__version__
copyright = "the terrainwarp authors"
extensions = ["sphinx.ext.autodoc", "sphinx.ext.napoleon", "myst_parser", "twdocs"]
source_suffix = {".rst": "restructuredtext", ".md": "markdown"}
exclude_patterns = ["_build"]
html_theme = "furo"
html_title = f"terrainwarp {release}"
html_static_path: list[str] = []

# Google-style docstrings; a class's Attributes section becomes field lists (its dataclass fields are not
# documented twice)
napoleon_google_docstring = True
napoleon_numpy_docstring = False
napoleon_use_ivar = True
napoleon_use_rtype = False
autodoc_typehints = "signature"
autodoc_preserve_defaults = True  # a default shows as it is written (MAX_TESS, not 64)
autodoc_class_signature = "separated"
autodoc_member_order = "bysource"
myst_heading_anchors = 3
