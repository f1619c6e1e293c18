"""Tests for vpr_nb.results: committed reproduce-profile results and their staleness check."""
from __future__ import annotations

import json
import math
import re
from pathlib import Path

import pytest

from vpr_nb import results

NOTEBOOKS = Path(__file__).resolve().parents[1] / "notebooks"


def test_save_then_load_round_trip(tmp_path):
    cfg = {"epochs": 10, "seeds": (0, 1, 2), "lr": 0.01}
    path = results.save("99_demo", cfg, {"R@1": {"T": [0.5, 0.6]}}, results_dir=tmp_path)
    doc = json.loads(path.read_text())
    assert doc["stamp"]["git commit"] and doc["stamp"]["torch"]
    got = results.load("99_demo", dict(cfg, seeds=[0, 1, 2]), results_dir=tmp_path)   # tuple == list
    assert got["results"] == {"R@1": {"T": [0.5, 0.6]}}


def test_load_refuses_stale_or_missing_results(tmp_path):
    results.save("99_demo", {"epochs": 10, "lr": 0.01}, {"x": 1}, results_dir=tmp_path)
    with pytest.raises(ValueError, match=r"stale.*\['epochs'\]"):
        results.load("99_demo", {"epochs": 12, "lr": 0.01}, results_dir=tmp_path)
    with pytest.raises(ValueError, match=r"stale.*\['seeds'\]"):
        results.load("99_demo", {"epochs": 10, "lr": 0.01, "seeds": [0]}, results_dir=tmp_path)
    with pytest.raises(FileNotFoundError, match="PROFILE = 'reproduce'"):
        results.load("98_none", {}, results_dir=tmp_path)
    with pytest.raises(ValueError, match="notebook stem"):
        results.load("../x", {}, results_dir=tmp_path)


def test_every_committed_result_belongs_to_a_notebook_that_loads_it():
    """A committed file that no notebook reads would be shown nowhere (and never checked)."""
    for path in sorted((NOTEBOOKS / "results").glob("*.json")):
        nb = NOTEBOOKS / f"{path.stem}.ipynb"
        assert nb.is_file(), f"{path.name} has no notebook {nb.name}"
        assert re.search(rf"results\.load\(\s*\\?[\"']{path.stem}", nb.read_text()), \
            f"{nb.name} never calls results.load('{path.stem}', ...)"


def test_load_refuses_results_of_other_backbone_weights(tmp_path):
    path = results.save("99_demo", {"epochs": 1}, {"x": 1}, results_dir=tmp_path)
    assert results.load("99_demo", {"epochs": 1}, results_dir=tmp_path)["course_backbone"] == results.backbone_fingerprint()
    doc = json.loads(path.read_text())
    doc["course_backbone"] = "0" * 64
    path.write_text(json.dumps(doc))
    with pytest.raises(ValueError, match="other course-backbone weights"):
        results.load("99_demo", {"epochs": 1}, results_dir=tmp_path)


def test_backbone_fingerprint_follows_tensors_not_file_bytes(tmp_path):
    import torch
    from vpr_nb.pretrain import CHECKPOINT
    state = torch.load(CHECKPOINT, weights_only=True)
    torch.save(state, tmp_path / "other_name.pt")                 # other archive name: other bytes, same tensors
    assert results.backbone_fingerprint(tmp_path / "other_name.pt") == results.backbone_fingerprint()
    state[next(iter(state))].view(-1)[0] += 1
    torch.save(state, tmp_path / "changed.pt")
    assert results.backbone_fingerprint(tmp_path / "changed.pt") != results.backbone_fingerprint()


def test_mean_std_and_paired_verdict():
    m, sd = results.mean_std([1.0, 2.0, 3.0])
    assert m == 2.0 and math.isclose(sd, 1.0)
    assert results.mean_std([4.0]) == (4.0, 0.0)
    assert "A is better" in results.paired_verdict([0.8, 0.81, 0.82], [0.5, 0.52, 0.5], "A", "B")
    assert "B is better" in results.paired_verdict([0.5, 0.52, 0.5], [0.8, 0.81, 0.82], "A", "B")
    assert "no verdict" in results.paired_verdict([0.5, 0.6, 0.4], [0.5, 0.4, 0.6], "A", "B")
    assert "one seed" in results.paired_verdict([0.5], [0.4])
    with pytest.raises(ValueError, match="same non-zero"):
        results.paired_verdict([0.5], [0.4, 0.3])
    with pytest.raises(ValueError, match="at least one"):
        results.mean_std([])


def test_print_table(capsys):
    results.print_table({"A": {"R@1": "0.500"}, "B": {"R@1": "0.600"}}, "title", label_width=5, col_width=7)
    assert capsys.readouterr().out.splitlines() == ["title", "           A      B", "  R@1  0.500  0.600"]
    with pytest.raises(ValueError, match="missing"):
        results.print_table({"A": {"R@1": "1"}, "B": {}}, "t")
    with pytest.raises(ValueError, match="non-empty"):
        results.print_table({}, "t")
