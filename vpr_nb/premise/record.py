"""A paper's premise record: the quantity its method exploits, on and off, and the method's paired gaps there.

Each premise notebook (03 DW-T-Loss, 05 SALAD, 07 CliqueMining) stores one record under the top-level
``"premise"`` key of its results file::

    {"quantity": "<what the method exploits>",
     "real data": {"value": <number or text>, "source": "<where it was measured or reported>"} or "not found",
     "worlds": {"on": {"value": <the quantity>, "test queries": <int>, ...},
                "off": {"value": ..., "test queries": ..., ...}},
     "comparisons": {"<method> − <baseline>": {"on": [paired per-seed differences], "off": [...]}}}

A gap is the mean of paired per-seed differences ``a_seed − b_seed`` with its standard error
``SE = sd / sqrt(n)`` (sample sd); its verdict word (:func:`verdict`) follows the numbers: **helps** when the
mean exceeds 2 SE, **hurts** when it is below −2 SE, otherwise **no measurable effect**. The notebooks print
:func:`gap_text` for every comparison and world, and a test checks the stored text against the stored record.
"""
from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

import numpy as np

WORLDS = ("on", "off")
VERDICTS = ("helps", "hurts", "no measurable effect")
MIN_SEEDS = 5          # paired seeds a comparison needs in a reproduce-profile record
MIN_TEST_QUERIES = 1000  # test queries a world needs there (one query is then at most 0.001 of R@1)


def _numbers(values, what: str) -> np.ndarray:
    try:
        arr = np.asarray(values, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"{what} must be a list of numbers, got {values!r}") from None
    if arr.ndim != 1 or len(arr) == 0:
        raise ValueError(f"{what} must be a non-empty list of numbers (one per seed), got shape {arr.shape}")
    if not np.isfinite(arr).all():
        raise ValueError(f"{what} holds NaN or inf: a failed run? re-run it or leave the seed out of every arm")
    return arr


def paired_differences(a_vals: Sequence[float], b_vals: Sequence[float], digits: int = 4) -> list[float]:
    """``[a_i − b_i]`` over paired seeds, rounded to ``digits`` (the record stores these)."""
    a, b = _numbers(a_vals, "a_vals"), _numbers(b_vals, "b_vals")
    if len(a) != len(b):
        raise ValueError(f"paired differences need one value per seed on both sides, got {len(a)} and {len(b)}")
    return [round(float(x), digits) for x in a - b]


def gap(diffs: Sequence[float]) -> tuple[float, float]:
    """Mean and standard error (sample sd / sqrt(n); 0 for one seed) of paired differences."""
    d = _numbers(diffs, "diffs")
    se = float(np.std(d, ddof=1) / math.sqrt(len(d))) if len(d) > 1 else 0.0
    return float(d.mean()), se


def verdict(diffs: Sequence[float]) -> str:
    """``"helps"`` (mean > 2 SE), ``"hurts"`` (mean < −2 SE) or ``"no measurable effect"``; one seed or a
    zero spread with a zero mean has no verdict beyond the last."""
    m, se = gap(diffs)
    if len(diffs) < 2:
        return "no measurable effect"
    if m > 2 * se:
        return "helps"
    if m < -2 * se:
        return "hurts"
    return "no measurable effect"


def gap_text(diffs: Sequence[float]) -> str:
    """``"+0.036 ± 0.009 (5 seeds): helps"``: the gap, its SE, the number of seeds and the verdict word."""
    m, se = gap(diffs)
    return f"{m:+.3f} ± {se:.3f} ({len(diffs)} seeds): {verdict(diffs)}"


def _check_world(name: str, world) -> dict:
    if not isinstance(world, Mapping) or "value" not in world or "test queries" not in world:
        raise ValueError(f"worlds[{name!r}] must be a dict with at least 'value' (the premise quantity there) and "
                         f"'test queries', got {world!r}")
    q = world["test queries"]
    if isinstance(q, bool) or not isinstance(q, (int, np.integer)) or q < 1:
        raise ValueError(f"worlds[{name!r}]['test queries'] must be a positive whole number, got {q!r}")
    return {**dict(world), "test queries": int(q)}


def premise_record(quantity: str, real_data, worlds: Mapping, comparisons: Mapping) -> dict:
    """The record stored under a results file's ``"premise"`` key (module docstring), checked.

    ``real_data``: ``{"value": ..., "source": "..."}`` or the string ``"not found"``; ``worlds``: ``"on"`` and
    ``"off"``, each a dict with ``"value"`` and ``"test queries"``; ``comparisons``: ``{"A − B": {"on":
    [diffs], "off": [diffs]}}`` (lists from :func:`paired_differences`)."""
    if not isinstance(quantity, str) or not quantity:
        raise ValueError(f"quantity must name the premise quantity, got {quantity!r}")
    if real_data != "not found" and not (isinstance(real_data, Mapping) and {"value", "source"} <= set(real_data)):
        raise ValueError(f"real_data must be 'not found' or a dict with 'value' and 'source', got {real_data!r}")
    if not isinstance(worlds, Mapping) or set(worlds) != set(WORLDS):
        raise ValueError(f"worlds must have exactly the keys {WORLDS}, got {list(worlds) if isinstance(worlds, Mapping) else worlds!r}")
    if not isinstance(comparisons, Mapping) or not comparisons:
        raise ValueError("comparisons must be a non-empty dict {'A − B': {'on': [...], 'off': [...]}}")
    comps = {}
    for name, per_world in comparisons.items():
        if not isinstance(per_world, Mapping) or set(per_world) != set(WORLDS):
            raise ValueError(f"comparisons[{name!r}] must have exactly the keys {WORLDS}")
        comps[str(name)] = {w: [float(x) for x in _numbers(per_world[w], f"comparisons[{name!r}][{w!r}]")]
                            for w in WORLDS}
    return {"quantity": quantity, "real data": real_data if real_data == "not found" else dict(real_data),
            "worlds": {w: _check_world(w, worlds[w]) for w in WORLDS}, "comparisons": comps}


def record_problems(record, min_seeds: int = MIN_SEEDS, min_test_queries: int = MIN_TEST_QUERIES) -> list[str]:
    """What a stored record lacks for the reproduce profile (empty: nothing): its shape (:func:`premise_record`),
    at least ``min_seeds`` paired differences per comparison and world, ``min_test_queries`` test queries."""
    try:
        rec = premise_record(record.get("quantity"), record.get("real data"), record.get("worlds"),
                             record.get("comparisons")) if isinstance(record, Mapping) else None
    except ValueError as err:
        return [str(err)]
    if rec is None:
        return [f"the premise record must be a dict, got {type(record).__name__}"]
    problems = [f"{name}, premise {w}: {len(d)} paired seeds, fewer than {min_seeds}"
                for name, per in rec["comparisons"].items() for w, d in per.items() if len(d) < min_seeds]
    problems += [f"world {w}: {rec['worlds'][w]['test queries']} test queries, fewer than {min_test_queries}"
                 for w in WORLDS if rec["worlds"][w]["test queries"] < min_test_queries]
    return problems


def verdict_lines(record: Mapping) -> list[str]:
    """One line per comparison and world, ``"DW-T − T-Loss, premise on: +0.036 ± 0.009 (5 seeds): helps"``,
    as the notebooks print them (and the consistency test reads them back)."""
    rec = premise_record(record["quantity"], record["real data"], record["worlds"], record["comparisons"])
    return [f"{name}, premise {w}: {gap_text(per[w])}" for name, per in rec["comparisons"].items() for w in WORLDS]
