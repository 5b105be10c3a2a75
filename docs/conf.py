"""Sphinx configuration: ``make docs`` builds docs/ into docs/_build/html with warnings as errors.

The pages are MyST Markdown; the API reference comes from the docstrings (numpydoc); the examples are a
sphinx-gallery gallery executed at build time; every measured number on a page comes from a generated file
through the ``measured`` role (``_ext/pmask_numbers.py``) or is a bound a test asserts.
"""
import os
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE / "_ext"))

import pmask  # noqa: E402  (the installed package: make docs runs in the project's venv)

project = "pmask"
author = "the pmask maintainers"
copyright = "2026, the pmask maintainers"
release = version = pmask.__version__

extensions = [
    "myst_parser",
    "sphinx.ext.autodoc",
    "sphinx.ext.autosummary",
    "sphinx.ext.mathjax",
    "sphinx.ext.viewcode",
    "numpydoc",
    "sphinx_gallery.gen_gallery",
    "pmask_numbers",
]
myst_enable_extensions = ["colon_fence", "deflist", "dollarmath"]
myst_heading_anchors = 3
source_suffix = {".md": "markdown", ".rst": "restructuredtext"}
exclude_patterns = ["_build", "generated/*.json", "auto_examples/*.ipynb", "auto_examples/*.py",
                    "auto_examples/*.zip", "auto_examples/*.md5", "auto_examples/*.codeobj.json"]
suppress_warnings = ["myst.header"]

autodoc_typehints = "none"
autodoc_member_order = "bysource"
autodoc_default_options = {"members": True, "show-inheritance": False}
autosummary_generate = False
numpydoc_show_class_members = False
numpydoc_validation_checks = set()
numpydoc_xref_param_type = False

sphinx_gallery_conf = {
    "examples_dirs": ["../examples"],
    "gallery_dirs": ["auto_examples"],
    "filename_pattern": r".*\.py$",      # every example runs at build time (CI builds the docs)
    "ignore_pattern": r"(__init__|_common)\.py$",
    "download_all_examples": False,
    "remove_config_comments": True,
    "plot_gallery": os.environ.get("PMASK_DOCS_RUN_EXAMPLES", "1") == "1",
    "abort_on_example_error": True,
    "min_reported_time": 1,
}

html_theme = "pydata_sphinx_theme"
html_title = f"pmask {release}"
html_static_path: list = []  # no static files of our own (an empty _static is not kept by git)
html_theme_options = {"navigation_depth": 2, "show_toc_level": 2, "secondary_sidebar_items": ["page-toc"],
                      "footer_start": ["copyright"], "footer_end": []}
html_show_sourcelink = False
# formulas in docstrings render with MathJax when the pages are read online; most are written out in Unicode
