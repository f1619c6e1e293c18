"""Where the package's data lives: the course backbone and the committed results, installed or in a checkout.

Both ship inside the wheel as package data (declared in ``pyproject.toml``), so a notebook finds them
from any working directory, whether ``vpr_nb`` is installed from a wheel (``pip install .``, Binder,
Colab) or editable from a clone (``make venv``):

- the course backbone and its card are package data of :mod:`vpr_nb.weights`
  (``vpr_nb/weights/course_backbone.pt`` + ``.json`` in the repository);
- the committed reproduce-profile results live in the repository's ``notebooks/results/``, beside the
  notebooks that display them; the wheel carries a copy as the data package ``vpr_nb.committed_results``
  (a setuptools ``package-dir`` mapping, see ``setup.py``).

A reproduce run *writes* results (:func:`results_dir_for_writing`): into the repository's
``notebooks/results/`` when ``vpr_nb`` runs from a checkout, where they are committed, or into the
folder named by the environment variable ``VPR_NB_RESULTS_DIR``; an installed package refuses rather
than write into ``site-packages``. ``VPR_NB_RESULTS_DIR``, when set, is also where results are read.
"""
from __future__ import annotations

import os
from importlib import resources
from pathlib import Path

RESULTS_DIR_ENV = "VPR_NB_RESULTS_DIR"
PACKAGE_DIR = Path(__file__).resolve().parent


def checkout_root() -> Path | None:
    """The repository folder when this ``vpr_nb`` is imported from a clone (editable install or
    ``PYTHONPATH``), else ``None`` (installed from a wheel into ``site-packages``)."""
    root = PACKAGE_DIR.parent
    if (root / "pyproject.toml").is_file() and (root / "notebooks" / "results").is_dir():
        return root
    return None


def _package_path(*parts: str) -> Path:
    # resolved from vpr_nb itself, a regular package (vpr_nb.committed_results has no __init__.py, and
    # files() of such a namespace package is not a path); installed wheels and clones are plain folders
    # (never zip imports), so the resource is a real path
    return Path(str(resources.files("vpr_nb").joinpath(*parts)))


def course_backbone_path() -> Path:
    """The committed course-backbone checkpoint (its card ``course_backbone.json`` lies beside it)."""
    return _package_path("weights", "course_backbone.pt")


def committed_results_dir() -> Path:
    """The folder the committed results are read from: ``$VPR_NB_RESULTS_DIR`` if set, else the
    repository's ``notebooks/results/`` in a checkout, else the copy installed with the package."""
    if os.environ.get(RESULTS_DIR_ENV):
        return Path(os.environ[RESULTS_DIR_ENV])
    root = checkout_root()
    if root is not None:
        return root / "notebooks" / "results"
    return _package_path("committed_results")


def results_dir_for_writing() -> Path:
    """The folder a reproduce run writes its results to; refuses (ValueError) for an installed package."""
    if os.environ.get(RESULTS_DIR_ENV):
        return Path(os.environ[RESULTS_DIR_ENV])
    root = checkout_root()
    if root is None:
        raise ValueError(f"vpr_nb is installed in {PACKAGE_DIR.parent}, not run from a clone of the course, so "
                         f"reproduce-profile results have no repository folder (notebooks/results/) to go to; "
                         f"run from a clone (make venv installs it editable) or set {RESULTS_DIR_ENV}=<folder>")
    return root / "notebooks" / "results"
