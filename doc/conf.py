"""Sphinx configuration of the hand_sog_tracker documentation (rosdoc2 layout: doc/conf.py).

Build: ``make docs`` (warnings are errors).  Markdown pages go through MyST; the API pages are
generated from the numpydoc docstrings (napoleon), the command-line pages from the tools'
argparse parsers (sphinx-argparse), the parameter table from ``hand_sog_tracker/ros/params.py``
(``_ext/hand_sog_docs.py``).
"""

from __future__ import annotations

import re
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

DOC = Path(__file__).resolve().parent
REPO = DOC.parent
sys.path.insert(0, str(DOC / "_ext"))
sys.path.insert(0, str(REPO))

project = "hand_sog_tracker"
author = "hand_sog_tracker maintainers"
copyright = "hand_sog_tracker maintainers, Apache-2.0"
release = ET.parse(REPO / "package.xml").getroot().findtext("version")
version = release

extensions = [
    "myst_parser",
    "sphinx.ext.autodoc",
    "sphinx.ext.napoleon",
    "sphinxarg.ext",
    "hand_sog_docs",
]
source_suffix = {".rst": "restructuredtext", ".md": "markdown"}
exclude_patterns = ["_build"]
root_doc = "index"

myst_enable_extensions = ["colon_fence", "deflist"]
myst_heading_anchors = 3

napoleon_google_docstring = False
napoleon_numpy_docstring = True
napoleon_use_rtype = False
napoleon_use_ivar = True  # "Attributes" as fields: a dataclass's fields are not described twice
autodoc_member_order = "bysource"
autodoc_typehints = "none"  # the numpydoc sections state types, shapes and units
autodoc_default_options = {"members": True, "show-inheritance": False}

html_theme = "alabaster"
html_title = f"hand_sog_tracker {release}"

# Types in the docstrings ("array, shape (n, 3), mm") are cross-referenced word by word; a word
# such as "shape" names several attributes.  Those ambiguous links resolve to the first match:
# not worth a warning.
# The notes in doc/notes/ come from several hands: a note that starts at "##" or skips a heading
# level still builds.
suppress_warnings = ["ref.python", "myst.header"]


_ABS = re.compile(r"(?<![|`\w])\|([\w.]+(?: [-+*/] [\w.]+)*)\|(?![|`\w])")


def _absolute_values(app, what, name, obj, options, lines: list[str]) -> None:
    """``|error|`` or ``|length - 1|`` in a docstring is an absolute value, not a reST substitution."""
    lines[:] = [_ABS.sub(r"``|\1|``", line) for line in lines]


def setup(app) -> None:
    app.connect("autodoc-process-docstring", _absolute_values)
