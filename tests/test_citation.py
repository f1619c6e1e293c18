"""CITATION.cff makes the course citable: Citation File Format 1.2.0 with its required keys, the LICENSE's
copyright holder as the author, the package's version, and the two papers the course reproduces with their
authors exactly."""
from __future__ import annotations

import re
import tomllib
from pathlib import Path

import pytest

import vpr_nb

yaml = pytest.importorskip("yaml")

ROOT = Path(__file__).resolve().parents[1]
PAPERS = {
    "Distance-Ranking-Based Weighted Triplet Loss for Visual Place Recognition":
        [("Xiong", "Yu"), ("Xu", "Shixiong"), ("Meng", "Gaofeng")],
    "Close, But Not There: Boosting Geographic Distance Sensitivity in Visual Place Recognition":
        [("Izquierdo", "Sergio"), ("Civera", "Javier")],
}


@pytest.fixture(scope="module")
def cff():
    path = ROOT / "CITATION.cff"
    assert path.is_file(), "CITATION.cff is missing at the repository root"
    doc = yaml.safe_load(path.read_text(encoding="utf-8"))
    assert isinstance(doc, dict), "CITATION.cff must be a YAML mapping"
    return doc


def test_the_required_keys_of_cff_1_2_0(cff):
    assert cff["cff-version"] == "1.2.0"
    for key in ("cff-version", "message", "title", "authors"):
        assert cff.get(key), f"CITATION.cff needs {key!r}"
    assert cff["title"] == "vpr-notebooks" and cff["type"] == "software"
    assert isinstance(cff["message"], str) and "cite" in cff["message"]
    assert cff["version"] == vpr_nb.__version__, "CITATION.cff's version must be vpr_nb.__version__"
    assert cff["license"] == tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["license"]["text"]


def test_the_author_is_the_copyright_holder_of_the_license(cff):
    holder = re.search(r"Copyright \(c\) \d{4}(?:-\d{4})? (.+)", (ROOT / "LICENSE").read_text()).group(1).strip()
    assert cff["authors"] == [{"name": holder}], f"the author must be the entity LICENSE names: {holder!r}"


def test_the_repository_is_only_given_where_pyproject_gives_it(cff):
    urls = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"].get("urls") or {}
    repository = urls.get("Repository") or urls.get("Source") or urls.get("Homepage")
    assert cff.get("repository-code") == repository, "repository-code must be pyproject's [project.urls] (or absent)"


def test_both_papers_are_referenced_with_their_authors(cff):
    refs = {ref["title"].strip(): ref for ref in cff["references"]}
    assert set(refs) == set(PAPERS)
    for title, authors in PAPERS.items():
        ref = refs[title]
        assert ref["type"] in ("generic", "article", "conference-paper"), ref["type"]
        assert [(a["family-names"], a["given-names"]) for a in ref["authors"]] == authors, title
    clique = refs["Close, But Not There: Boosting Geographic Distance Sensitivity in Visual Place Recognition"]
    assert clique["year"] == 2024 and "ECCV" in clique["conference"]["name"]
