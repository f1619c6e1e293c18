"""Comparing a notebook's stored text outputs with a re-run's, with a declared numeric tolerance.

A training notebook's printed numbers are exact on one machine but not across machines: the CPU's
vector width (AVX2 / AVX-512), the vendor's BLAS kernels (MKL picks other code on other CPUs) and
oneDNN's convolutions round in other orders, and a few hundred optimiser steps turn a last-bit
difference into a retrieval that ranks one query differently (an R@1 of 0.416 on one CPU, 0.421 on
another). nbval compares outputs as strings. A cell whose numbers come from such a computation says
so in its source with the marker comment

    # NBVAL_TOLERANCE=0.02            (absolute, on every number written with a decimal point)
    # NBVAL_TOLERANCE=0.02 rel=0.05   (or the larger of 0.02 and 5 % of the stored value)

and :func:`tolerant_equal` then accepts a re-run whose text is the stored text with each decimal number
within that tolerance. Everything else must still match exactly: the words, the layout, every integer
(counts, sizes, epochs), the number of numbers. Cells without the marker are compared exactly, as
nbval does. ``notebooks/conftest.py`` applies this inside nbval's comparison.
"""
from __future__ import annotations

import math
import re

# the marker line: "# NBVAL_TOLERANCE=<abs>", optionally " rel=<r>", optionally followed by a comment
MARKER = re.compile(r"^\s*#\s*NBVAL_TOLERANCE\s*=\s*(\S+)(?:\s+rel\s*=\s*(\S+))?(?:\s.*)?$", re.M)
# a decimal number: optional sign, digits, a point, digits, optional exponent (integers are not matched)
_DECIMAL = re.compile(r"(?<![\w.])[-+−]?\d+\.\d+(?:[eE][-+]?\d+)?(?![\w.])")


def cell_tolerance(source: str) -> tuple[float, float] | None:
    """(absolute, relative) tolerance declared by a ``# NBVAL_TOLERANCE=`` line of a cell, or None."""
    m = MARKER.search(source or "")
    if m is None:
        return None
    try:
        abs_tol, rel_tol = float(m.group(1)), float(m.group(2) or 0.0)
    except ValueError:
        raise ValueError(f"cannot read the tolerance in {m.group(0).strip()!r}: write e.g. "
                         f"'# NBVAL_TOLERANCE=0.02' or '# NBVAL_TOLERANCE=0.02 rel=0.05'") from None
    if not (0 <= abs_tol < math.inf and 0 <= rel_tol < 1):
        raise ValueError(f"{m.group(0).strip()!r}: the absolute tolerance must be >= 0 and rel in [0, 1)")
    return abs_tol, rel_tol


def _value(token: str) -> float:
    return float(token.replace("−", "-"))


def tolerant_equal(reference: str, test: str, abs_tol: float, rel_tol: float = 0.0) -> bool:
    """True when ``test`` is ``reference`` with every decimal number within the tolerance
    (``|test − ref| <= max(abs_tol, rel_tol·|ref|)``) and everything else identical."""
    if reference == test:
        return True
    ref_parts, test_parts = _DECIMAL.split(reference), _DECIMAL.split(test)
    if ref_parts != test_parts:           # other words, layout, integers or count of numbers
        return False
    for r, t in zip(_DECIMAL.findall(reference), _DECIMAL.findall(test)):
        a, b = _value(r), _value(t)
        if not abs(b - a) <= max(abs_tol, rel_tol * abs(a)):
            return False
    return True


def align_to_reference(reference: str, test: str, abs_tol: float, rel_tol: float = 0.0) -> str:
    """``reference`` when ``test`` equals it within the tolerance (so a string comparison then passes),
    else ``test`` unchanged (so the comparison fails and shows the real difference)."""
    return reference if tolerant_equal(reference, test, abs_tol, rel_tol) else test
