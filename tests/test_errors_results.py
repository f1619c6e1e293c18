"""Broken results files and non-finite per-seed values end in one clear ValueError naming the file or seed;
a results file is read strictly: every number finite and in its metric's range, or a ValueError naming the file
and the key path."""
import json
import math
from pathlib import Path

import pytest

from vpr_nb import results, verdict


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
    with pytest.raises(ValueError, match=r"NetVLAD, seed 3: the value is nan, not a finite number"):
        verdict.paired_differences([0.5, 0.6, 0.55], [0.4, math.nan, 0.45], "GeM", "NetVLAD", seeds=[0, 3, 4])
    with pytest.raises(ValueError, match=r"GeM, entry 1: the value is inf"):
        verdict.paired_differences([0.5, math.inf], [0.4, 0.3], "GeM", "NetVLAD")
    with pytest.raises(ValueError, match=r"mean_std values, entry 2: the value is nan"):
        results.mean_std([0.5, 0.6, float("nan")])
    with pytest.raises(ValueError, match=r"R@1 of SALAD, entry 0: 'n/a' is not a number"):
        results.mean_std(["n/a"], "R@1 of SALAD")
    with pytest.raises(ValueError, match="seeds names 2 seeds but there are 1 values"):
        verdict.paired_differences([0.5], [0.4], seeds=[0, 1])


GOOD = {"rows": {"T-Loss": {"R@1": [0.5, 0.6, 0.7], "best epoch": [3, 0, 12], "start R@1": [0.4, 0.4, 0.4]}},
        "val R@1 per lr": {"T-Loss": {"0.001": [0.5, 0.55]}}, "lr": {"T-Loss": 0.001}, "seconds": 12.5,
        "fixed": {"raw pixels": {"p(0,10 m) Eq.3": 0.1, "top-5 Kendall tau": -0.2, "mean cosine": -0.05,
                                 "slope per 10 m, Eq.2": -3.5, "dim": 128}},
        "gradient ratios": {"max": {"W-T-Loss": 9.4}}, "R@1 gain": -0.05,
        "trained weights": {"seed0": {"file": "x.pt", "bytes": 100, "keys": 4, "sha256": "ab"}}}


@pytest.fixture()
def saved_rows(tmp_path):
    return results.save("99_demo", {"epochs": 1}, GOOD, results_dir=tmp_path)


def test_every_committed_results_file_still_loads():
    """The strict reading accepts every committed file, through the notebooks' own call (its config)."""
    folder = Path(__file__).resolve().parents[1] / "notebooks" / "results"
    names = sorted(p.stem for p in folder.glob("*.json"))
    assert names, "no committed results found"
    for name in names:
        doc = results.load(name, json.loads((folder / f"{name}.json").read_text())["config"])
        assert doc["results"], name


def test_good_results_of_every_kind_load(saved_rows):
    assert _load(saved_rows)["results"] == GOOD


@pytest.mark.parametrize("old, new, match", [
    # JSON's non-standard tokens, which Python's json reads as numbers
    ('"R@1": [0.5, 0.6, 0.7]', '"R@1": [0.5, 0.6, NaN]', r"results\.rows\.T-Loss\.R@1\[2\] is NaN \(a JSON token"),
    ('"R@1": [0.5, 0.6, 0.7]', '"R@1": [Infinity, 0.6, 0.7]', r"results\.rows\.T-Loss\.R@1\[0\] is Infinity"),
    ('"seconds": 12.5', '"seconds": -Infinity', r"results\.seconds is -Infinity"),
    ('"epochs": 1', '"epochs": NaN', r"config\.epochs is NaN"),
    # a number too large for a float
    ('"R@1": [0.5, 0.6, 0.7]', '"R@1": [0.5, 1e999, 0.7]', r"results\.rows\.T-Loss\.R@1\[1\] is inf \(a number too large"),
    ('"slope per 10 m, Eq.2": -3.5', '"slope per 10 m, Eq.2": -1e999', r"results\.fixed\.raw pixels\.\"slope per 10 m, Eq\.2\" is -inf"),
    # NaN as report.jsonable writes it
    ('"seconds": 12.5', '"seconds": "nan"', r"results\.seconds is 'nan' \(a NaN or inf"),
    # out of its metric's range
    ('"R@1": [0.5, 0.6, 0.7]', '"R@1": [0.5, 1.2, 0.7]', r"results\.rows\.T-Loss\.R@1\[1\] is 1\.2, but it must be a recall, probability or share, in \[0, 1\]"),
    ('"start R@1": [0.4, 0.4, 0.4]', '"start R@1": [0.4, -0.1, 0.4]', r"results\.rows\.T-Loss\.start R@1\[1\] is -0\.1, but it must be a recall"),
    ('"0.001": [0.5, 0.55]', '"0.001": [0.5, 55]', r"results\.val R@1 per lr\.T-Loss\.\"0\.001\"\[1\] is 55, but it must be a recall"),
    ('"p(0,10 m) Eq.3": 0.1', '"p(0,10 m) Eq.3": 1.5', r"results\.fixed\.raw pixels\.\"p\(0,10 m\) Eq\.3\" is 1\.5, but it must be a recall, probability"),
    ('"best epoch": [3, 0, 12]', '"best epoch": [3, -1, 12]', r"results\.rows\.T-Loss\.best epoch\[1\] is -1, but it must be a count, a whole number >= 0"),
    ('"best epoch": [3, 0, 12]', '"best epoch": [3, 0, 2.5]', r"results\.rows\.T-Loss\.best epoch\[2\] is 2\.5, but it must be a count"),
    ('"bytes": 100', '"bytes": -100', r"results\.trained weights\.seed0\.bytes is -100, but it must be a count"),
    ('"seconds": 12.5', '"seconds": -1', r"results\.seconds is -1, but it must be a duration in seconds, >= 0"),
    ('"lr": {"T-Loss": 0.001}', '"lr": {"T-Loss": 0}', r"results\.lr\.T-Loss is 0, but it must be a learning rate, > 0"),
    ('"mean cosine": -0.05', '"mean cosine": 1.5', r"results\.fixed\.raw pixels\.mean cosine is 1\.5, but it must be a cosine or rank correlation, in \[-1, 1\]"),
])
def test_a_non_finite_or_out_of_range_number_names_the_file_and_its_key_path(saved_rows, old, new, match):
    text = json.dumps(json.loads(saved_rows.read_text()))         # one line: the replacements below are exact
    assert text.count(old) == 1, old
    saved_rows.write_text(text.replace(old, new))
    with pytest.raises(ValueError, match=rf"99_demo\.json: {match}.*re-make it with `make reproduce`"):
        _load(saved_rows)


def test_save_refuses_what_load_would_refuse(tmp_path):
    bad = {"rows": {"T": {"R@1": [0.5, math.nan]}}}
    with pytest.raises(ValueError, match=r"refusing to write 99_demo\.json: results\.rows\.T\.R@1\[1\] is 'nan'"):
        results.save("99_demo", {"epochs": 1}, bad, results_dir=tmp_path)
    with pytest.raises(ValueError, match=r"results\.R@5 is 1\.01, but it must be a recall"):
        results.save("99_demo", {"epochs": 1}, {"R@5": 1.01}, results_dir=tmp_path)
    assert not list(tmp_path.iterdir())
