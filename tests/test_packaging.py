"""Packaging facts a newcomer relies on: the Python version, one version string, declared extras."""
import re
import sys
import tomllib
from pathlib import Path

import vpr_nb

ROOT = Path(__file__).resolve().parents[1]
PYPROJECT = tomllib.loads((ROOT / "pyproject.toml").read_text())


def test_running_python_satisfies_requires_python():
    spec = PYPROJECT["project"]["requires-python"]
    minimum = tuple(int(x) for x in re.fullmatch(r">=(\d+)\.(\d+)", spec).groups())
    assert sys.version_info[:2] >= minimum, f"Python {sys.version.split()[0]} does not satisfy requires-python {spec}"
    assert f"{minimum[0]}.{minimum[1]}" in (ROOT / "README.md").read_text(), "README must state the minimum Python"


def test_one_version_string_and_declared_extras():
    assert PYPROJECT["project"]["dynamic"] == ["version"]
    assert PYPROJECT["tool"]["setuptools"]["dynamic"]["version"] == {"attr": "vpr_nb.__version__"}
    assert re.fullmatch(r"\d+\.\d+\.\d+", vpr_nb.__version__)
    extras = PYPROJECT["project"]["optional-dependencies"]
    pinned = {re.split(r"[=<>]", line)[0].strip().lower() for line in (ROOT / "environment.txt").read_text().splitlines()
              if line.strip() and not line.startswith("#")}
    declared = {re.split(r"[\[=<>]", d)[0].lower() for group in extras.values() for d in group} - {"vpr_nb"}
    assert declared <= pinned, f"extras not pinned in environment.txt: {sorted(declared - pinned)}"
    assert {"nbformat", "nbclient", "papermill", "ipywidgets"} <= declared
    assert (ROOT / "LICENSE").is_file() and PYPROJECT["project"]["license"]
