"""The notebooks' prose agrees with their stored outputs: numbers, directions and verdicts (``tests/claims.py``
states the rules and what they cannot check; ``python tests/claims.py`` prints every finding)."""
from __future__ import annotations

import copy
import json
from pathlib import Path

import pytest

from claims import check_notebook, check_path, sentences

NOTEBOOKS = sorted((Path(__file__).resolve().parents[1] / "notebooks").glob("[0-9][0-9]_*.ipynb"))


def _param(path: Path):
    return pytest.param(path, id=path.stem)


@pytest.mark.parametrize("path", [_param(p) for p in NOTEBOOKS])
def test_prose_agrees_with_the_outputs(path):
    findings = check_path(path)
    for f in findings:
        print(f)
    assert not findings, (f"{path.name}: {len(findings)} sentence(s) contradict the stored outputs "
                          "(fix the text; tests/claims.py says how each rule reads):\n"
                          + "\n".join(str(f) for f in findings))


# --- it bites: notebook 02 with its old wrong takeaway ------------------------------------------------------

OLD_02 = "It has not converged: validation R@1 still rose from 0.602 to 0.684 in the last epoch."


def test_the_old_takeaway_of_02_is_flagged():
    path = next(p for p in NOTEBOOKS if p.name.startswith("02_"))
    nb = json.loads(path.read_text(encoding="utf-8"))
    bad = copy.deepcopy(nb)
    for cell in bad["cells"]:
        src = "".join(cell["source"])
        if cell["cell_type"] == "markdown" and "validation R@1 still rose from 0.602 to" in src:
            cell["source"] = src.replace("rose from 0.602 to 0.647", "rose from 0.602 to 0.684")
            break
    else:
        bad["cells"].append({"cell_type": "markdown", "metadata": {}, "source": OLD_02})
    findings = check_notebook(bad, path.name, "02")
    assert [f.rule for f in findings] == ["number"] and "0.684" in findings[0].why, findings
    assert not check_notebook(nb, path.name, "02"), "the stored notebook 02 should pass"


# --- each rule on tiny notebooks ------------------------------------------------------------------------------

OUTPUT = """epoch    loss  val R@1
    1   0.337    0.586
    2   0.315    0.602
best epoch 2 (val R@1 0.602)

method              R@1  mean cos
trained           0.748     0.684
scores 0.5 0.9
R@1: NetVLAD − GeM = +0.031 ± 0.015 (SE, 5 seeds): NetVLAD is better
R@1: Max-W − Max = +0.002 ± 0.007 (SE, 5 seeds): within 2 SE, no verdict
DW-T-Loss − T-Loss, premise on: -0.018 ± 0.009 (5 seeds): hurts
R@1: cliques vs sparse only: inconclusive: the baseline does not improve on its starting point
p(0,10 m) Eq.3     0.043     0.022
"""


def _nb(*markdown: str) -> dict:
    """A notebook in nbformat v4 shape: one code cell printing OUTPUT, then the markdown cells."""
    code = {"cell_type": "code", "metadata": {}, "source": "print(...)", "execution_count": 1,
            "outputs": [{"output_type": "stream", "name": "stdout", "text": OUTPUT}]}
    md = [{"cell_type": "markdown", "metadata": {}, "source": m} for m in markdown]
    return {"nbformat": 4, "nbformat_minor": 5, "metadata": {}, "cells": [code] + md}


def _rules(*markdown: str, **kw) -> list[str]:
    return [f.rule for f in check_notebook(_nb(*markdown), "fake", **kw)]


@pytest.mark.parametrize("text, flagged", [
    ("Validation R@1 reached 0.684.", True),             # 0.684 is printed, but as the mean cosine
    ("Validation R@1 reached 0.602.", False),
    ("Its mean cosine is 0.684.", False),
    ("Test R@1 is 0.75 here.", False),                   # compared at the precision written
    ("Test R@1 is 0.749 here.", True),
    ("The best epoch is 2.", False),
    ("The best epoch is 3.", True),
    ("R@1 reaches 0.9 once.", False),                    # printed without a quantity: cannot tell, skipped
    ("R@1 reaches 0.777 once.", True),                   # printed nowhere
    ("About 0.999 of the queries agree.", False),        # names no quantity: not checked
    ("R@1 is about 0.7.", False),                        # hedged: not checked
    ("At lr 0.5 the loss falls.", False),                # a setting, not a value of the loss
    ("The paper reports R@1 0.812.", False),             # a paper's number
    ("NetVLAD beats GeM by +0.031 ± 0.015 R@1.", False),
    ("NetVLAD beats GeM by +0.041 ± 0.015 R@1.", True),
])
def test_numbers_must_be_printed_under_their_quantity(text, flagged):
    assert _rules(text) == (["number"] if flagged else [])


def test_committed_results_back_numbers(tmp_path):
    (tmp_path / "99_x.json").write_text(json.dumps({"results": {"GeM": {"R@1": [0.80, 0.81], "best epoch": [3, 4]}}}))
    assert _rules("GeM reaches R@1 0.805 on average.", number="99", results_dir=tmp_path) == []
    assert _rules("GeM reaches R@1 0.81 on one seed.", number="99", results_dir=tmp_path) == []
    assert _rules("GeM reaches R@1 0.815.", number="99", results_dir=tmp_path) == ["number"]
    assert _rules("GeM reaches R@1 0.805 on average.") == ["number"]          # without the results


@pytest.mark.parametrize("text, flagged", [
    ("Validation R@1 rose from 0.586 to 0.602.", False),
    ("Validation R@1 fell from 0.586 to 0.602.", True),
    ("The loss falls from 0.337 (epoch 1) to 0.315.", False),
    ("The loss climbs from 0.337 to 0.315.", True),
    ("Triplets halve $p(0, 10)$ (0.043 → 0.022).", False),
    ("Triplets raise $p(0, 10)$ (0.043 → 0.022).", True),
    ("It gives a better start (0.748 vs 0.684).", False),
    ("It gives a worse start (0.748 vs 0.684).", True),
    ("The caps sit far above R@1 (0.748 vs 0.684).", False),
    ("The caps sit below R@1 (0.748 vs 0.684).", True),
    ("Triplets are better on $p(0, 10)$ (0.022 vs 0.043).", False),  # lower p is better
    ("Triplets are better on $p(0, 10)$ (0.043 vs 0.022).", True),
    ("R@1 0.748 vs 0.684, about as good.", False),                   # no direction word: nothing to check
])
def test_direction_words_must_match_the_order(text, flagged):
    assert "direction" in _rules(text) if flagged else "direction" not in _rules(text)


@pytest.mark.parametrize("text, flagged", [
    ("NetVLAD beats GeM on this world.", False),
    ("GeM beats NetVLAD on this world.", True),
    ("GeM does not beat NetVLAD.", False),
    ("NetVLAD does not beat GeM.", True),
    ("*NetVLAD − GeM*: no measurable effect.", True),
    ("*NetVLAD − GeM*: NetVLAD is better.", False),
    ("Max-W vs Max is within 2 SE.", False),
    ("Max-W beats Max.", True),
    ("Max-W is below Max.", True),
    ("*DW-T-Loss − T-Loss, premise on*: hurts.", False),
    ("*DW-T-Loss − T-Loss, premise on*: helps.", True),
    ("*DW-T-Loss − T-Loss, premise on*: no measurable effect.", True),
    ("Cliques beat sparse only here.", True),                        # the printed verdict is inconclusive
    ("Cliques vs sparse only is inconclusive.", False),
    ("The layer alone beats its start.", False),                     # names nothing printed: not checked
])
def test_verdict_words_must_match_the_printed_verdict(text, flagged):
    assert _rules(text) == (["verdict"] if flagged else [])


def test_escape_hatch_needs_a_reason():
    assert _rules("<!-- claim: skip: misread, the number is a setting --> Validation R@1 reached 0.684.") == []
    assert _rules("<!-- claim: skip --> Validation R@1 reached 0.684.") == ["number"]


def test_sentences_keep_abbreviations_and_drop_tables_headings_and_code():
    md = ("## R@1 0.999\n\nBy Eq. (4) the loss is 0.337. Next sentence.\n\n| a | R@1 0.999 |\n|---|---|\n\n"
          "```\nR@1 0.999\n```\n* a list item, e.g. this one.")
    assert [s for s, _ in sentences(md)] == ["By Eq. (4) the loss is 0.337.", "Next sentence.",
                                             "a list item, e.g. this one."]


@pytest.mark.parametrize("text, flagged", [
    ("Max-W beats Max.", True),                                              # printed: no verdict
    ("**Prediction.** Max-W beats Max; a tie falsifies it.", False),         # a prediction states no outcome
    ("If the weight helps, Max-W beats Max.", False),
    ("Max-W would beat Max with another loss.", False),
])
def test_predictions_are_not_claims(text, flagged):
    assert (_rules(text) == ["verdict"]) == flagged
