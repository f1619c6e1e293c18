"""Paired gaps over seeds, the control gate and the verdict words: the course's one rule for "helps".

Every comparison in the course pairs seeds: method ``a`` and method ``b`` train on the same seeds, and the
per-seed differences ``d_i = a_i − b_i`` are what is tested. The rule, in three parts:

* **The test.** A paired two-sided t test (Student's t test on the differences, ``n − 1`` degrees of freedom:
  ``t = mean / SE``, ``SE = sd / sqrt(n)`` with the sample sd; :func:`scipy.stats.ttest_1samp` against 0).
* **The family.** The comparisons printed in one table are one family, and their p values are adjusted by
  Holm's step-down procedure (S. Holm, "A simple sequentially rejective multiple test procedure",
  Scandinavian Journal of Statistics 6, 1979), which keeps the chance of *any* false "helps"/"hurts" in the
  table at most 5 %.
* **The words.** ``"helps"`` (``a`` beats ``b``) or ``"hurts"`` only when the Holm-adjusted p is below
  :data:`ALPHA` (0.05); otherwise ``"no measurable effect"``. With 5 seeds (4 df) a lone comparison needs
  ``|t| > 2.78``; "beyond 2 SE" (``|t| > 2``) would call 12 % of pure-noise gaps a verdict.

A **control gate** is one test, not part of a family: the baseline of a comparison must beat what it is
compared with (its start, or a named reference such as the frozen backbone + GeM) by a one-sided paired t test
at 5 %. When it does not, the comparison's verdict is ``"inconclusive"``, and the message names the reference.
"""
from __future__ import annotations

import math
from collections.abc import Collection, Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from scipy import stats

ALPHA = 0.05
WORDS = ("helps", "hurts", "no measurable effect")
INCONCLUSIVE = "inconclusive"


def finite_values(values, what: str, seeds: Sequence | None = None) -> np.ndarray:
    """``values`` as a 1-D float array; ValueError naming ``what`` and the entry (``seed s`` when ``seeds`` is
    given, else its position) that is not a finite number, or saying that the list is empty."""
    if isinstance(values, (str, bytes, Mapping)) or np.ndim(values) != 1:
        raise ValueError(f"{what} must be a list of numbers (one per seed), got {values!r}")
    values = list(values)
    if not values:
        raise ValueError(f"{what} is empty: give one number per seed (at least one seed)")
    if seeds is not None and len(seeds) != len(values):
        raise ValueError(f"{what}: seeds names {len(seeds)} seeds but there are {len(values)} values; give one "
                         f"seed per value")
    out = np.empty(len(values))
    for i, v in enumerate(values):
        where = f"seed {seeds[i]}" if seeds is not None else f"entry {i}"
        try:
            out[i] = float(v)
        except (TypeError, ValueError):
            raise ValueError(f"{what}, {where}: {v!r} is not a number") from None
        if not math.isfinite(out[i]):
            raise ValueError(f"{what}, {where}: the value is {out[i]}, not a finite number (a diverged or failed "
                             f"run?); re-run that seed or leave it out of every compared method")
    return out


def paired_differences(a_vals, b_vals, a: str = "a_vals", b: str = "b_vals", *, seeds: Sequence | None = None,
                       digits: int | None = None) -> list[float]:
    """``[a_i − b_i]`` over paired seeds (rounded to ``digits`` when given: the premise records store 4).

    Both lists must hold one finite number per seed, in the same seed order; ValueError otherwise."""
    x, y = finite_values(a_vals, a, seeds), finite_values(b_vals, b, seeds)
    if len(x) != len(y):
        raise ValueError(f"a paired difference needs one value per seed on both sides, got {len(x)} for {a} and "
                         f"{len(y)} for {b}; compare the same seeds")
    d = x - y
    return [round(float(v), digits) if digits is not None else float(v) for v in d]


def gap(diffs: Sequence[float]) -> tuple[float, float]:
    """Mean and standard error (sample sd / sqrt(n); 0 for one seed) of paired differences."""
    d = finite_values(diffs, "diffs")
    return float(d.mean()), float(d.std(ddof=1) / math.sqrt(len(d))) if len(d) > 1 else 0.0


def _testable(d: np.ndarray) -> bool:
    """Two or more seeds with some spread: without them a t test has no estimate of the seed-to-seed noise."""
    return len(d) > 1 and float(d.std(ddof=1)) > 1e-12 * max(1.0, float(abs(d).max()))


def holm(pvalues: Sequence[float]) -> list[float]:
    """Holm's (1979) step-down adjusted p values, in the order given.

    Sort the ``m`` p values; the ``k``-th smallest (k = 0, 1, ...) is multiplied by ``m − k``, capped at 1, and
    made no smaller than the adjusted p before it. A comparison is significant at level α when its adjusted p
    is below α; the chance of any false rejection in the family is then at most α."""
    try:
        p = np.asarray(pvalues, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"pvalues must be a list of numbers, got {pvalues!r}") from None
    if p.ndim != 1 or not len(p) or not ((p >= 0) & (p <= 1)).all():      # NaN fails the range check too
        raise ValueError(f"pvalues must be a non-empty list of p values, each in [0, 1], got {pvalues!r}")
    adjusted, running = [0.0] * len(p), 0.0
    for k, i in enumerate(np.argsort(p, kind="stable")):
        running = max(running, min(1.0, (len(p) - k) * float(p[i])))
        adjusted[i] = running
    return adjusted


def _p(p: float) -> str:
    """A p value in 3 decimals, rounded down (so "0.049" is always below 0.05 and "0.050" never is)."""
    return "< 0.001" if p < 0.001 else f"{math.floor(p * 1000) / 1000:.3f}"


def _t(t: float) -> str:
    return f"{round(t, 1) + 0.0:.1f}"          # + 0.0: no "-0.0"


@dataclass(frozen=True)
class Gate:
    """A control gate (:func:`control_gate`): did ``baseline`` beat ``reference``?"""
    baseline: str
    reference: str
    mean: float
    se: float
    t: float            # nan when there is nothing to test (one seed, no spread)
    df: int
    p: float            # one-sided; 1.0 when there is nothing to test
    n: int
    passed: bool

    def numbers(self) -> str:
        """``"T-Loss − its start = +0.113 ± 0.006 (5 seeds, t 18.8, one-sided p < 0.001)"``."""
        if math.isnan(self.t):
            stats_ = f"{_seeds(self.n)}, no spread to test"
        else:
            stats_ = f"{_seeds(self.n)}, t {_t(self.t)}, one-sided p {_p(self.p)}"
        return f"{self.baseline} − {self.reference} = {self.mean:+.3f} ± {self.se:.3f} ({stats_})"

    def text(self) -> str:
        """``"T-Loss − its start = +0.113 ± 0.006 (5 seeds, t 18.8, one-sided p < 0.001): passes"``."""
        return f"{self.numbers()}: {'passes' if self.passed else 'fails'}"

    def inconclusive(self) -> str:
        """``"inconclusive: sparse only does not beat frozen backbone + GeM (-0.142 ± 0.006, 5 seeds)"``."""
        return (f"{INCONCLUSIVE}: {self.baseline} does not beat {self.reference} "
                f"({self.mean:+.3f} ± {self.se:.3f}, {_seeds(self.n)})")


def _seeds(n: int) -> str:
    return f"{n} seed" if n == 1 else f"{n} seeds"


def control_gate(baseline_vals, reference_vals, baseline: str = "baseline",
                 reference: str = "its starting point") -> Gate:
    """Does ``baseline`` beat ``reference`` over paired seeds? A one-sided paired t test at 5 %.

    ``reference_vals`` is one value per seed (the baseline's start, epoch 0, per seed), or one number when the
    reference is the same for every seed (a frozen backbone); then the test is the one-sample t test of the
    baseline against it. The gate passes when ``mean(baseline − reference) > 0`` with one-sided p < 0.05
    (``n − 1`` df). A gate is one comparison, never part of a Holm family. One seed, or differences without any
    spread, give no estimate of the noise: the gate fails (``t`` is nan, ``p`` 1). NaN/inf, empty or
    mismatched lists raise ValueError."""
    base = finite_values(baseline_vals, f"{baseline} (baseline values)")
    if isinstance(reference_vals, (int, float, np.number)) and not isinstance(reference_vals, bool):
        reference_vals = [reference_vals] * len(base)
    ref = finite_values(reference_vals, f"{reference} (reference values)")
    if len(ref) != len(base):
        raise ValueError(f"control_gate needs one value of {reference!r} per seed of {baseline!r} (or one number "
                         f"for every seed), got {len(base)} baseline and {len(ref)} reference values")
    d = base - ref
    m, se = gap(d)
    if not _testable(d):
        return Gate(baseline, reference, m, se, math.nan, len(d) - 1, 1.0, len(d), False)
    res = stats.ttest_1samp(d, 0.0, alternative="greater")
    p = float(res.pvalue)
    return Gate(baseline, reference, m, se, float(res.statistic), len(d) - 1, p, len(d), p < ALPHA)


@dataclass(frozen=True)
class Verdict:
    """One comparison's verdict within its family (:func:`verdicts`)."""
    mean: float
    se: float
    t: float            # nan when there is nothing to test (one seed, no spread)
    df: int
    p: float            # two-sided, before the correction; 1.0 when there is nothing to test
    p_holm: float       # Holm-adjusted over the family
    n: int
    family: int         # the number of comparisons the family holds
    word: str           # "helps", "hurts", "no measurable effect" or "inconclusive"
    gate: Gate | None = None

    def text(self) -> str:
        """``"+0.036 ± 0.009 (5 seeds, t 4.1, Holm p 0.030 over 4 comparisons): helps"``; a comparison whose
        gate failed: the gate's ``"inconclusive: ..."`` message."""
        if self.word == INCONCLUSIVE and self.gate is not None:
            return self.gate.inconclusive()
        if math.isnan(self.t):
            return f"{self.mean:+.3f} ± {self.se:.3f} ({_seeds(self.n)}, no spread to test): {self.word}"
        p = f"Holm p {_p(self.p_holm)} over {self.family} comparisons" if self.family > 1 else f"p {_p(self.p)}"
        return f"{self.mean:+.3f} ± {self.se:.3f} ({_seeds(self.n)}, t {_t(self.t)}, {p}): {self.word}"


def verdicts(comparisons: Mapping[str, Sequence[float]], *, lower_is_better: Collection[str] = (),
             gates: Mapping[str, Gate] | None = None) -> dict[str, Verdict]:
    """The verdicts of one family: ``{name: paired per-seed differences a − b}`` → ``{name: Verdict}``.

    Each comparison gets a paired two-sided t test (``n − 1`` df); the p values are Holm-adjusted over all the
    comparisons given (:func:`holm`). ``"helps"`` when the adjusted p < 0.05 and ``a`` is the better (a
    positive mean, or a negative one for a name in ``lower_is_better``, such as a mis-ordering probability),
    ``"hurts"`` when ``b`` is; otherwise ``"no measurable effect"``. One seed, or differences without any
    spread (every seed gave the same gap), give no estimate of the seed-to-seed noise, so nothing can be told
    apart from it: ``"no measurable effect"`` (p taken as 1).

    ``gates``: ``{name: control_gate(...)}`` for comparisons against a fine-tuned baseline; a failed gate makes
    that comparison ``"inconclusive"``. It still counts in the family (the family is the table as printed)."""
    if not isinstance(comparisons, Mapping) or not comparisons:
        raise ValueError("comparisons must be a non-empty dict {'A − B': [per-seed differences]}: one family, "
                         "the comparisons of one table")
    if isinstance(lower_is_better, (str, bool)) or not isinstance(lower_is_better, Collection):
        raise ValueError(f"lower_is_better must be a list of comparison names (those whose metric is better lower), "
                         f"got {lower_is_better!r}")
    if not isinstance(gates or {}, Mapping):
        raise ValueError(f"gates must be a dict {{comparison name: control_gate(...)}}, got {gates!r}")
    gates = dict(gates or {})
    unknown = sorted(set(lower_is_better) - set(comparisons)) + sorted(set(gates) - set(comparisons))
    if unknown:
        raise ValueError(f"lower_is_better and gates name comparisons that are not in the family: {unknown}; "
                         f"use the keys of comparisons ({list(comparisons)})")
    tests = {}
    for name, diffs in comparisons.items():
        d = finite_values(diffs, f"comparisons[{name!r}]")
        m, se = gap(d)
        if _testable(d):
            res = stats.ttest_1samp(d, 0.0)
            tests[name] = (m, se, float(res.statistic), float(res.pvalue), len(d))
        else:
            tests[name] = (m, se, math.nan, 1.0, len(d))
    adjusted = dict(zip(tests, holm([t[3] for t in tests.values()])))
    out = {}
    for name, (m, se, t, p, n) in tests.items():
        word = WORDS[2]
        if adjusted[name] < ALPHA:
            word = WORDS[0] if (m > 0) != (name in lower_is_better) else WORDS[1]
        gate = gates.get(name)
        if gate is not None and not gate.passed:
            word = INCONCLUSIVE
        out[name] = Verdict(m, se, t, n - 1, p, adjusted[name], n, len(tests), word, gate)
    return out


def verdict(diffs: Sequence[float], *, lower_is_better: bool = False) -> Verdict:
    """The verdict of one comparison alone (a family of one: no correction). See :func:`verdicts`."""
    return verdicts({"a − b": diffs}, lower_is_better=("a − b",) if lower_is_better else ())["a − b"]


def family_note(family: Mapping[str, Verdict], what: str = "this table") -> str:
    """The line a notebook prints under a table of verdicts: ``"Holm over the 4 comparisons of this table"``."""
    if not family:
        raise ValueError("family_note needs the verdicts of a non-empty family (the dict verdicts() returned)")
    n = len(family)
    return f"Holm over the {n} comparisons of {what}" if n > 1 else f"one comparison in {what}: no correction"
