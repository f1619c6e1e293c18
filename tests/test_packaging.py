"""Packaging facts a newcomer relies on: the Python version, one version string, declared extras."""
import importlib
import re
import sys
import tomllib
from pathlib import Path

import pytest

import vpr_nb

ROOT = Path(__file__).resolve().parents[1]
PYPROJECT = tomllib.loads((ROOT / "pyproject.toml").read_text())


def test_running_python_satisfies_requires_python():
    spec = PYPROJECT["project"]["requires-python"]
    minimum = tuple(int(x) for x in re.fullmatch(r">=(\d+)\.(\d+)", spec).groups())
    assert sys.version_info[:2] >= minimum, f"Python {sys.version.split()[0]} does not satisfy requires-python {spec}"
    assert f"{minimum[0]}.{minimum[1]}" in (ROOT / "README.md").read_text(), "README must state the minimum Python"


def _pins(name):
    """{package: version} of a pinned requirements file (comments, options and -r lines skipped)."""
    pins = {}
    for line in (ROOT / name).read_text().splitlines():
        line = line.split("#")[0].strip()
        if line and not line.startswith("-"):
            pkg, _, version = line.partition("==")
            pins[pkg.strip().lower().replace("_", "-")] = version.strip()
    return pins


def _names(requirements):
    return {re.split(r"[\[=<>; ]", d)[0].lower().replace("_", "-") for d in requirements} - {"vpr-nb"}


def test_one_version_string_and_declared_extras():
    assert PYPROJECT["project"]["dynamic"] == ["version"]
    assert PYPROJECT["tool"]["setuptools"]["dynamic"]["version"] == {"attr": "vpr_nb.__version__"}
    assert re.fullmatch(r"\d+\.\d+\.\d+", vpr_nb.__version__)
    extras = PYPROJECT["project"]["optional-dependencies"]
    student, dev = _pins("environment.txt"), _pins("requirements-dev.txt")
    runtime = _names(PYPROJECT["project"]["dependencies"])
    assert runtime | _names(extras["notebooks"]) <= set(student), "runtime and notebook needs must be pinned in environment.txt"
    assert _names(extras["test"]) <= set(student) | set(dev), "the test extra must be pinned in requirements-dev.txt"
    assert {"nbformat", "nbclient", "papermill", "ipywidgets"} <= _names(extras["notebooks"])
    assert (ROOT / "LICENSE").is_file() and PYPROJECT["project"]["license"]


def test_students_get_no_developer_tools_and_every_file_agrees_on_torch():
    student, dev = _pins("environment.txt"), _pins("requirements-dev.txt")
    tools = {"pytest", "nbval", "ruff", "playwright", "pytorch-metric-learning", "networkx"}
    assert not tools & set(student), f"developer tools in the student environment: {sorted(tools & set(student))}"
    assert tools <= set(dev) and not set(dev) & set(student), "requirements-dev.txt adds the tools to environment.txt"
    assert "-r environment.txt" in (ROOT / "requirements-dev.txt").read_text()
    assert "networkx" not in _names(PYPROJECT["project"]["dependencies"]), "vpr_nb never imports networkx"
    binder = _pins("binder/requirements.txt")
    assert binder["torch"] == student["torch"] + "+cpu", "Binder's CPU torch must be environment.txt's version"
    assert (ROOT / "binder" / "runtime.txt").read_text().strip() == "python-3.11"
    assert "pip install --no-cache-dir --no-deps ." in (ROOT / "binder" / "postBuild").read_text()
    wanted = _names(PYPROJECT["project"]["dependencies"])
    for group in PYPROJECT["project"]["optional-dependencies"].values():
        wanted |= _names(group)
    missing = wanted - set(_pins("constraints-newest.txt"))
    assert not missing, f"constraints-newest.txt misses {sorted(missing)}: make newest-constraints PY=python3.13"


def test_packages_are_discovered_and_the_commands_are_listed():
    assert "packages" not in PYPROJECT["tool"]["setuptools"], "packages are found by setup.py (every vpr_nb*)"
    assert PYPROJECT["tool"]["setuptools"]["package-dir"] == {"vpr_nb.committed_results": "notebooks/results"}
    from vpr_nb.__main__ import COMMANDS
    scripts = PYPROJECT["project"]["scripts"]
    assert {s: f"{m}:main" for s, m, _ in COMMANDS if s} == scripts
    for _, module, _ in COMMANDS:
        assert callable(getattr(importlib.import_module(module), "main")), module


def test_python_m_vpr_nb_lists_the_commands(capsys):
    from vpr_nb.__main__ import COMMANDS, main
    assert main([]) == 0
    out = capsys.readouterr().out
    assert all(f"python -m {m}" in out for _, m, _ in COMMANDS) and "vpr-train" in out
    assert main(["train"]) == 2 and capsys.readouterr().err.startswith("error: ")


def test_results_are_read_and_written_where_package_data_says(tmp_path, monkeypatch):
    from vpr_nb import package_data, results
    assert package_data.checkout_root() == ROOT                      # the tests run from the clone
    assert package_data.committed_results_dir() == package_data.results_dir_for_writing() == ROOT / "notebooks" / "results"
    assert package_data.course_backbone_path() == ROOT / "vpr_nb" / "weights" / "course_backbone.pt"
    monkeypatch.setenv(package_data.RESULTS_DIR_ENV, str(tmp_path))
    monkeypatch.setenv(results.ALLOW_DIRTY_ENV, "1")     # where the file goes, in a clean or an edited clone
    assert results.save("99_demo", {"epochs": 1}, {"R@1": 0.5}) == tmp_path / "99_demo.json"
    assert results.load("99_demo", {"epochs": 1})["results"] == {"R@1": 0.5}
    monkeypatch.delenv(package_data.RESULTS_DIR_ENV)
    monkeypatch.setattr(package_data, "checkout_root", lambda: None)  # as installed from a wheel
    with pytest.raises(ValueError, match="VPR_NB_RESULTS_DIR"):
        results.save("99_demo", {"epochs": 1}, {"R@1": 0.5})
    assert package_data.committed_results_dir() == ROOT / "vpr_nb" / "committed_results"   # the installed copy's place
