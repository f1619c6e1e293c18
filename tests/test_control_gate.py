"""The control gate (vpr_nb.verdict): a paired verdict only over a baseline that beats its starting point
(tests/test_verdict.py tests the rule itself)."""
import math

import pytest

from vpr_nb import verdict as V


def control_gate(baseline_vals, start_vals, baseline="baseline", start="its starting point"):
    gate = V.control_gate(baseline_vals, start_vals, baseline, start)
    return gate.passed, gate.numbers()


def gated_verdict(a_vals, b_vals, start_vals, a="A", b="B", start="its starting point"):
    """One comparison over a gated baseline, as the notebooks print it."""
    name = f"{a} − {b}"
    diffs = V.paired_differences(a_vals, b_vals, f"{a} (method values)", f"{b} (baseline values)")
    v = V.verdicts({name: diffs}, gates={name: V.control_gate(b_vals, start_vals, b, start)})[name]
    return f"{name}: {v.text()}" + (f" [control: {v.gate.text()}]" if v.word != "inconclusive" else "")

START = [0.70, 0.71, 0.70, 0.72, 0.70]                  # the epoch-0 weights, per seed
GOOD_BASE = [0.80, 0.81, 0.79, 0.82, 0.80]              # the baseline fine-tune: +0.10, t 49


def test_control_passes_when_the_baseline_beats_its_start():
    passed, text = control_gate(GOOD_BASE, START, "T-Loss", "frozen")
    assert passed and text == "T-Loss − frozen = +0.098 ± 0.002 (5 seeds, t 49.0, one-sided p < 0.001)"


def test_control_fails_below_or_close_to_its_start_and_on_one_seed():
    assert not control_gate([0.69, 0.70, 0.71, 0.70, 0.70], START)[0]            # worse than the start
    assert not control_gate([0.71, 0.70, 0.72, 0.71, 0.71], START)[0]            # +0.004 ± 0.005: one-sided p 0.2
    passed, text = control_gate([0.9], [0.7])
    assert not passed and text.endswith("(1 seed, no spread to test)")
    assert control_gate(GOOD_BASE, 0.70)[0]                                       # one number: the same start for all


def test_verdict_only_over_a_working_control():
    better = [0.85, 0.87, 0.84, 0.88, 0.85]
    v = gated_verdict(better, GOOD_BASE, START, "DW-T", "T", "frozen")
    assert v.startswith("DW-T − T: +0.054 ± 0.002 (5 seeds, t 22.0, p < 0.001): helps [control: T − frozen = +0.098")
    worse = [0.75, 0.77, 0.74, 0.78, 0.75]
    assert ": hurts [control:" in gated_verdict(worse, GOOD_BASE, START, "DW-T", "T")
    close = [0.80, 0.82, 0.79, 0.81, 0.80]
    assert ": no measurable effect [control:" in gated_verdict(close, GOOD_BASE, START, "DW-T", "T")


def test_a_failing_control_makes_the_verdict_inconclusive_and_names_the_reference():
    base = [0.66, 0.70, 0.64, 0.68, 0.62]               # the baseline ends below its start (as 03's T-Loss once did)
    v = gated_verdict([0.30, 0.31, 0.30, 0.29, 0.30], base, START, "DW-T", "T", "frozen backbone + GeM")
    assert v == "DW-T − T: inconclusive: T does not beat frozen backbone + GeM (-0.046 ± 0.012, 5 seeds)"


def test_nan_and_mismatched_seeds_are_refused():
    with pytest.raises(ValueError, match=r"B \(baseline values\), entry 2: the value is nan, not a finite number"):
        gated_verdict(GOOD_BASE, [0.8, 0.8, math.nan, 0.8, 0.8], START, "A", "B")
    with pytest.raises(ValueError, match=r"A \(method values\), entry 0: the value is nan"):
        gated_verdict([math.nan] * 5, GOOD_BASE, START, "A", "B")
    with pytest.raises(ValueError, match=r"reference values\), entry 0: the value is nan"):
        control_gate(GOOD_BASE, float("nan"))
    with pytest.raises(ValueError, match="one value of 'its starting point' per seed of 'baseline'"):
        control_gate(GOOD_BASE, START[:3])
    with pytest.raises(ValueError, match="compare the same seeds"):
        gated_verdict(GOOD_BASE[:4], GOOD_BASE, START)
    with pytest.raises(ValueError, match="is not a number"):
        control_gate(["a"], [0.1])
