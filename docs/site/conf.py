"""Sphinx configuration of the course's website (``make site``; ``docs/site/build.py`` stages the sources and runs Sphinx).

The site is built from what is committed and never executes a notebook: myst-nb reads the stored outputs
(``nb_execution_mode = "off"``). The source folder Sphinx reads is a staged copy of README.md, docs/*.md,
notebooks/NN_*.ipynb and docs/site/*.md (``docs/site/build.py``), laid out with the repository's own paths, so a page's
path is its file's path in the repository (what the Binder and Colab launch buttons open).

Settings come from the environment that ``docs/site/build.py`` sets:

``VPR_SITE_ROOT``       the repository (or tiny test copy) being built: its ``pyproject.toml`` and its files
``VPR_SITE_REFERENCE``  ``1`` (default): the package reference and the commands' ``--help`` pages; ``0``: none
``VPR_SITE_BRANCH``     the branch the launch buttons open (default ``main``)

The repository's address is kept in one place, ``pyproject.toml``'s ``[project.urls] Repository``; without it
(today) the pages have no launch buttons, and the build says so in one line.
"""
from __future__ import annotations

import os
import sys
import tomllib
from pathlib import Path

SITE_DIR = Path(__file__).resolve().parent
sys.path.insert(0, str(SITE_DIR))

import vpr_site  # noqa: E402  (docs/site/vpr_site.py: this site's own Sphinx extension)

ROOT = Path(os.environ.get("VPR_SITE_ROOT") or SITE_DIR.parent).resolve()
WITH_REFERENCE = os.environ.get("VPR_SITE_REFERENCE", "1") != "0"
PYPROJECT = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))
REPOSITORY = vpr_site.repository_url(PYPROJECT)
BRANCH = os.environ.get("VPR_SITE_BRANCH") or "main"

project = "vpr-notebooks"
author = "the vpr-notebooks authors"
copyright = "the vpr-notebooks authors, MIT licence"   # noqa: A001  (Sphinx's name)
release = version = PYPROJECT["project"].get("version") or vpr_site.package_version(ROOT)

root_doc = "README"                     # README.md is the home page; index.html redirects to it
extensions = [
    "myst_nb",                          # notebooks (.ipynb, stored outputs) and Markdown (MyST) pages
    "sphinx.ext.mathjax",               # equations, typeset in the browser by a local MathJax (no CDN)
    "sphinx.ext.autodoc",
    "sphinx.ext.autosummary",
    "sphinx.ext.napoleon",              # the few Google-style "Args:" sections
    "vpr_site",
]
templates_path = [str(SITE_DIR / "_templates")]      # absolute: autosummary reads it from the (staged) srcdir
exclude_patterns = ["**/.ipynb_checkpoints"]

# --- notebooks: never executed ------------------------------------------------------------------------------------
nb_execution_mode = "off"
nb_merge_streams = False                # outputs in the order the notebook stores them
nb_ipywidgets_js: dict = {}             # no widget JavaScript from a CDN: a widget cell shows its static output
myst_enable_extensions = ["dollarmath", "amsmath"]
myst_heading_anchors = 4                # GitHub's heading anchors, as README and docs/ link to them
myst_dmath_double_inline = True

# --- equations: MathJax 3.2.2 served from the site itself (sphinx-mathjax-offline's files) -------------------------
mathjax_path = vpr_site.MATHJAX_SCRIPT  # relative: _static/mathjax/tex-chtml.js, copied there at the end of the build

# --- package reference ----------------------------------------------------------------------------------------------
autosummary_generate = WITH_REFERENCE
autosummary_imported_members = False
autodoc_default_options = {"members": True, "show-inheritance": True}
autodoc_member_order = "bysource"
autodoc_typehints = "description"
autodoc_preserve_defaults = True
napoleon_google_docstring = True
napoleon_numpy_docstring = False

# --- the theme ------------------------------------------------------------------------------------------------------
html_theme = "sphinx_book_theme"
html_title = "vpr-notebooks"
html_static_path = ["_static"]
html_last_updated_fmt = None
html_theme_options = {
    "home_page_in_toc": True,
    "show_navbar_depth": 1,
    "use_download_button": True,        # the page's source: the stored .ipynb of a notebook page
    "use_fullscreen_button": False,
    "navigation_with_keys": False,
    **vpr_site.launch_options(REPOSITORY, BRANCH),
}

vpr_site_root = str(ROOT)
vpr_site_repository = REPOSITORY or ""
vpr_site_branch = BRANCH
