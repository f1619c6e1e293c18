"""Only the package list: everything else is in pyproject.toml.

pyproject.toml alone cannot both discover packages automatically and add a package whose folder lies
outside vpr_nb/: ``vpr_nb.committed_results`` is the repository's ``notebooks/results/`` (mapped in
pyproject's ``package-dir``), so the committed results stay beside the notebooks and still install with
the wheel. Every ``vpr_nb*`` package with an ``__init__.py`` is found here, so a new subpackage needs no edit.
"""
from setuptools import find_packages, setup

setup(packages=find_packages(include=["vpr_nb", "vpr_nb.*"]) + ["vpr_nb.committed_results"])
