"""The course's one verdict rule (vpr_nb.verdict): the paired t test, Holm's correction over a family, the words,
the control gate, and input validation."""
import math

import numpy as np
import pytest

from vpr_nb.verdict import (ALPHA, INCONCLUSIVE, WORDS, control_gate, family_note, gap, holm, paired_differences,
                            verdict, verdicts)

NULL = [0.01, -0.01, 0.0, 0.02, -0.02]          # mean 0: nothing to see
MODEST = [0.02, 0.03, 0.0, 0.03, 0.02]          # t 3.65 on 4 df: p 0.022 alone


def test_the_t_test_on_a_hand_example():
    # d = 1, 2, 3: mean 2, sd 1, SE 1/sqrt(3), t = 2 sqrt(3) on 2 df, whose two-sided p has a closed form:
    # p = 1 − t / sqrt(2 + t²) (Student's t with 2 df)
    v = verdict([1.0, 2.0, 3.0])
    t = 2 * math.sqrt(3)
    assert (v.mean, v.n, v.df, v.family) == (2.0, 3, 2, 1)
    assert v.se == pytest.approx(1 / math.sqrt(3)) and v.t == pytest.approx(t)
    assert v.p == pytest.approx(1 - t / math.sqrt(2 + t * t)) == pytest.approx(0.07418, abs=1e-5)
    assert v.p_holm == v.p and v.word == "no measurable effect"          # p 0.074: not below 0.05
    # 1 df (two seeds) is a Cauchy distribution: p = 1 − 2 atan(t) / pi
    v = verdict([1.0, 3.0])
    assert v.t == pytest.approx(2.0) and v.p == pytest.approx(1 - 2 * math.atan(2.0) / math.pi)
    assert gap([1.0, 2.0, 3.0]) == pytest.approx((2.0, 1 / math.sqrt(3)))


def test_two_standard_errors_are_not_enough_at_five_seeds():
    # mean −0.018, SE 0.009: beyond 2 SE (the old rule said "hurts"), but t −2.1 on 4 df has p 0.10
    d = [-0.0296, -0.0266, -0.0126, 0.0114, -0.0326]
    v = verdict(d)
    assert abs(v.mean) > 2 * v.se and 2 < abs(v.t) < 2.776 and v.p > ALPHA
    assert v.word == "no measurable effect"


@pytest.mark.parametrize("diffs, lower, word", [([0.03, 0.04, 0.02, 0.05, 0.03], False, "helps"),
                                                ([-0.03, -0.04, -0.02, -0.05, -0.03], False, "hurts"),
                                                ([-0.03, -0.04, -0.02, -0.05, -0.03], True, "helps"),
                                                (NULL, False, "no measurable effect"),
                                                ([0.05], False, "no measurable effect"),
                                                ([0.05] * 5, False, "no measurable effect")])
def test_the_words(diffs, lower, word):
    v = verdict(diffs, lower_is_better=lower)
    assert v.word == word and v.text().endswith(f": {word}") and word in WORDS


def test_one_seed_and_zero_spread_say_so():
    assert verdict([0.05]).text() == "+0.050 ± 0.000 (1 seed, no spread to test): no measurable effect"
    v = verdict([0.05] * 5)
    assert math.isnan(v.t) and v.p == 1.0 and v.text() == ("+0.050 ± 0.000 (5 seeds, no spread to test): "
                                                            "no measurable effect")


def test_holm_on_a_hand_example():
    # sorted: 0.005 × 4 = 0.02, 0.01 × 3 = 0.03, 0.03 × 2 = 0.06, 0.04 × 1 = 0.04 → kept at 0.06 (step-down)
    assert holm([0.01, 0.04, 0.03, 0.005]) == pytest.approx([0.03, 0.06, 0.06, 0.02])
    assert holm([0.02, 0.021]) == pytest.approx([0.04, 0.04])         # never below an earlier adjusted p
    assert holm([0.6, 0.7]) == [1.0, 1.0]                              # capped at 1
    assert holm([0.03]) == [0.03]                                      # a family of one: unchanged
    p = np.random.default_rng(0).uniform(0, 0.2, 9)
    adj = np.array(holm(p))
    assert (adj >= p).all() and (np.diff(adj[np.argsort(p)]) >= 0).all()


def test_a_family_is_corrected_together():
    alone = verdict(MODEST)
    assert alone.word == "helps" and alone.p == pytest.approx(0.0217, abs=1e-3)
    family = verdicts({"A − B": MODEST, "C − B": NULL, "D − B": NULL[::-1], "E − B": [0.0, 0.01, -0.01, 0.0, 0.01]})
    v = family["A − B"]
    assert v.p == alone.p and v.p_holm == pytest.approx(4 * alone.p) and v.family == 4
    assert v.word == "no measurable effect"
    assert v.text() == "+0.020 ± 0.005 (5 seeds, t 3.7, Holm p 0.086 over 4 comparisons): no measurable effect"
    assert alone.text() == "+0.020 ± 0.005 (5 seeds, t 3.7, p 0.021): helps"
    assert family_note(family) == "Holm over the 4 comparisons of this table"
    assert list(family) == ["A − B", "C − B", "D − B", "E − B"]           # the caller's order


def test_a_p_value_is_printed_rounded_down():
    # Holm p 0.0498 must not print as 0.050 next to "helps"
    v = verdicts({"a": [0.0]})["a"]
    assert v.text().startswith("+0.000 ± 0.000")
    from vpr_nb.verdict import _p
    assert _p(0.0498) == "0.049" and _p(0.05) == "0.050" and _p(0.0004) == "< 0.001"


def test_the_gate_is_one_sided_and_names_its_reference():
    start = [0.70, 0.71, 0.70, 0.72, 0.70]
    gate = control_gate([0.80, 0.81, 0.79, 0.82, 0.80], start, "T-Loss", "its start")
    assert gate.passed and gate.df == 4 and gate.p < 0.001
    assert gate.text().startswith("T-Loss − its start = +0.098 ± 0.") and gate.text().endswith("< 0.001): passes")
    assert not control_gate([0.69, 0.70, 0.71, 0.70, 0.70], start).passed            # below its start
    small = control_gate([0.71, 0.70, 0.72, 0.71, 0.71], start)                       # +0.004 ± 0.005
    assert not small.passed and 0.05 < small.p < 0.5
    # t 2.7 on 4 df: one-sided p 0.026 passes the gate; the same gap as a two-sided comparison does not "help"
    gain = [0.01, 0.03, 0.0, 0.02, 0.01]
    assert control_gate(gain, [0.0] * 5).passed and verdict(gain).word == "no measurable effect"
    assert control_gate(gain, [0.0] * 5).p == pytest.approx(verdict(gain).p / 2)
    assert not control_gate([0.9], [0.7]).passed                                      # one seed
    assert control_gate([0.80, 0.81, 0.79, 0.82, 0.80], 0.70).passed                  # one number for every seed
    frozen = [0.64, 0.65, 0.63, 0.65, 0.64]
    gate = control_gate([0.50, 0.51, 0.49, 0.50, 0.50], frozen, "sparse only", "frozen backbone + GeM")
    assert gate.inconclusive() == "inconclusive: sparse only does not beat frozen backbone + GeM (-0.142 ± 0.002, 5 seeds)"
    # a comparison against that baseline is inconclusive, and says why
    family = verdicts({"cliques − sparse only": MODEST, "cliques − random": NULL},
                      gates={"cliques − sparse only": gate})
    assert family["cliques − sparse only"].word == INCONCLUSIVE and family["cliques − sparse only"].family == 2
    assert family["cliques − sparse only"].text() == gate.inconclusive()


def test_paired_differences():
    assert paired_differences([0.9, 0.8], [0.85, 0.82], digits=4) == [0.05, -0.02]
    assert paired_differences(np.array([1.0, 2.0]), [0.5, 0.5]) == [0.5, 1.5]


@pytest.mark.parametrize("call, match", [
    (lambda: verdict([0.1, math.nan, 0.2]), r"entry 1: the value is nan, not a finite number.*re-run that seed"),
    (lambda: verdict([]), r"is empty: give one number per seed"),
    (lambda: verdict("0.1"), r"must be a list of numbers"),
    (lambda: verdict([0.1, "x"]), r"entry 1: 'x' is not a number"),
    (lambda: verdicts({}), r"non-empty dict"),
    (lambda: verdicts({"a": [1.0, 2.0]}, lower_is_better=["b"]), r"not in the family: \['b'\]"),
    (lambda: verdicts({"a": [1.0, 2.0]}, lower_is_better=True), r"must be a list of comparison names"),
    (lambda: verdicts({"a": [1.0, 2.0]}, gates=["a"]), r"gates must be a dict"),
    (lambda: paired_differences([0.5, 0.6], [0.4]), r"one value per seed on both sides, got 2 for a_vals and 1"),
    (lambda: paired_differences([0.5, math.inf], [0.4, 0.3], "GeM", "NetVLAD", seeds=[0, 3]),
     r"GeM, seed 3: the value is inf"),
    (lambda: paired_differences([0.5], [0.4], seeds=[0, 1]), r"seeds names 2 seeds but there are 1 values"),
    (lambda: control_gate([0.8] * 5, [0.7] * 3), r"one value of 'its starting point' per seed of 'baseline'"),
    (lambda: control_gate([0.8] * 5, math.nan), r"reference values\), entry 0: the value is nan"),
    (lambda: holm([0.2, 1.5]), r"each in \[0, 1\]"),
    (lambda: holm([math.nan]), r"each in \[0, 1\]"),
    (lambda: holm([]), r"non-empty"),
    (lambda: family_note({}), r"non-empty family"),
])
def test_bad_input_is_refused_with_what_to_do(call, match):
    with pytest.raises(ValueError, match=match):
        call()


def test_one_comparison_alone_as_a_sentence():
    """A comparison alone (a family of one: no correction), as 04's and 06's tables once printed each line."""
    from vpr_nb import verdict as V

    def said(a, b, **kw):
        return V.verdict(V.paired_differences(a, b, "A", "B"), **kw).text()
    assert said([0.8, 0.81, 0.82], [0.5, 0.52, 0.5]) == "+0.303 ± 0.009 (3 seeds, t 34.4, p < 0.001): helps"
    assert said([0.5, 0.52, 0.5], [0.8, 0.81, 0.82]).endswith(": hurts")
    assert said([0.5, 0.6, 0.4], [0.5, 0.4, 0.6]).endswith(": no measurable effect")
    # a mis-ordering probability: lower is better, so the larger values lose
    assert said([0.3, 0.31, 0.32], [0.1, 0.12, 0.1], lower_is_better=True).endswith(": hurts")
    assert said([0.1, 0.12, 0.1], [0.3, 0.31, 0.32], lower_is_better=True).endswith(": helps")
    assert "1 seed, no spread to test" in said([0.5], [0.4])
    with pytest.raises(ValueError, match="compare the same seeds"):
        said([0.5], [0.4, 0.3])
