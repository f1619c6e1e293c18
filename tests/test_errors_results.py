"""Broken results files and non-finite per-seed values end in one clear ValueError naming the file or seed."""
import json
import math

import pytest

from vpr_nb import results


@pytest.fixture()
def saved(tmp_path):
    path = results.save("99_demo", {"epochs": 1}, {"R@1": {"A": [0.5, 0.6]}}, results_dir=tmp_path)
    return path, json.loads(path.read_text())


def _load(path):
    return results.load("99_demo", {"epochs": 1}, results_dir=path.parent)


def test_a_truncated_results_file_names_the_file_and_the_fix(saved):
    path, _ = saved
    path.write_text(path.read_text()[:-40])
    with pytest.raises(ValueError, match=r"99_demo\.json is not valid JSON \(.* line \d+, column \d+; truncated\?\); "
                                         r"restore it with `git checkout -- notebooks/results/99_demo\.json`"):
        _load(path)
    path.write_bytes(b'{"config": "\xff"}')
    with pytest.raises(ValueError, match=r"99_demo\.json is not UTF-8 text"):
        _load(path)


@pytest.mark.parametrize("mutate, match", [
    (lambda d: [d], r"holds a JSON array, not a results object"),
    (lambda d: {**d, "config": [1]}, r"its 'config' entry is a JSON array, not an object"),
    (lambda d: {k: v for k, v in d.items() if k != "results"}, r"has no 'results' entry"),
    (lambda d: {**d, "results": None}, r"its 'results' entry is a JSON null, not an object"),
])
def test_a_malformed_results_file_names_the_file(saved, mutate, match):
    path, doc = saved
    path.write_text(json.dumps(mutate(doc)))
    with pytest.raises(ValueError, match=rf"99_demo\.json.*{match}.*PROFILE = 'reproduce'"):
        _load(path)


def test_a_nan_seed_never_reaches_a_verdict():
    with pytest.raises(ValueError, match=r"paired_verdict: NetVLAD, seed 3: the value is nan, not a finite number"):
        results.paired_verdict([0.5, 0.6, 0.55], [0.4, math.nan, 0.45], "GeM", "NetVLAD", seeds=[0, 3, 4])
    with pytest.raises(ValueError, match=r"paired_verdict: GeM, entry 1: the value is inf"):
        results.paired_verdict([0.5, math.inf], [0.4, 0.3], "GeM", "NetVLAD")
    with pytest.raises(ValueError, match=r"mean_std values, entry 2: the value is nan"):
        results.mean_std([0.5, 0.6, float("nan")])
    with pytest.raises(ValueError, match=r"R@1 of SALAD, entry 0: 'n/a' is not a number"):
        results.mean_std(["n/a"], "R@1 of SALAD")
    with pytest.raises(ValueError, match="seeds names 2 seeds"):
        results.paired_verdict([0.5], [0.4], seeds=[0, 1])
