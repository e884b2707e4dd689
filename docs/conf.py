"""Sphinx configuration of the flexjoint-harness manual (``sphinx-build -W docs docs/_build/html``).

The pages are MyST Markdown (they read as Markdown on a forge too); the tutorials are MyST notebooks that
myst-nb executes on every build, so a command that stops working fails the build. They run the ``flexjoint``
command and ``import harness`` of this checkout: its root is put first on ``PYTHONPATH`` for the kernels and the
commands they start. The API reference comes from the numpydoc docstrings of ``harness.__all__``, the command
reference from the command line itself (each command's ``--help``).
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

DOCS = Path(__file__).resolve().parent
ROOT = DOCS.parent
sys.path[:0] = [str(ROOT), str(DOCS)]  # harness from this checkout; _api, _cli (generated pages) beside this file
os.environ["PYTHONPATH"] = os.pathsep.join([str(ROOT), *filter(None, [os.environ.get("PYTHONPATH")])])
os.environ.setdefault("FLEXJOINT_WORKERS", "2")  # the local cluster's size, whatever the machine
os.environ.setdefault("COLUMNS", "110")  # the commands' tables as wide as a page

from harness.numerics import pin_numerics  # noqa: E402

pin_numerics()  # before anything loads numpy: the kernels and the commands they start compute as the CLI does

from _api import write_api_page  # noqa: E402
from _cli import write_cli_page  # noqa: E402

import harness  # noqa: E402

write_api_page(DOCS / "reference" / "_api.md")  # every name of harness.__all__, generated on every build
write_cli_page(DOCS / "reference" / "_cli.md")  # every command's --help, generated on every build

project = "flexjoint-harness"
author = "the flexjoint-harness authors"
copyright = "the flexjoint-harness authors, BSD-2-Clause"  # noqa: A001
release = version = harness.__version__

extensions = [
    "myst_nb",
    "sphinx.ext.autodoc",
    "sphinx.ext.autosummary",
    "sphinx.ext.mathjax",
    "numpydoc",
]

source_suffix = {".rst": "restructuredtext", ".md": "myst-nb"}
exclude_patterns = ["_build", "jupyter_execute", "**/.ipynb_checkpoints", "reference/_api.md", "reference/_cli.md"]
root_doc = "index"

# MyST and the executed tutorials
myst_enable_extensions = ["colon_fence", "deflist", "dollarmath", "substitution"]
myst_heading_anchors = 3
nb_execution_mode = os.environ.get("FLEXJOINT_DOCS_EXECUTE", "cache")  # "force" to re-run, "off" to skip
nb_execution_cache_path = str(DOCS / "_build" / ".jupyter_cache")
nb_execution_timeout = 900  # s per cell: `flexjoint run` takes 30-50 s on 2 cores
nb_execution_raise_on_error = True  # a failing command fails the build
nb_merge_streams = True
nb_execution_show_tb = True

# API reference: numpydoc docstrings, type hints in the signatures
autodoc_typehints = "signature"
autodoc_member_order = "bysource"
autodoc_default_options = {"members": False}
numpydoc_show_class_members = False
numpydoc_class_members_toctree = False
numpydoc_xref_param_type = False

html_theme = "pydata_sphinx_theme"
html_title = "flexjoint-harness"
html_static_path: list[str] = []
html_theme_options = {
    "navigation_with_keys": False,
    "show_toc_level": 2,
    "footer_start": ["copyright"],
    "footer_end": [],
}
html_context = {"default_mode": "light"}
nitpicky = False
suppress_warnings = ["mystnb.unknown_mime_type"]
