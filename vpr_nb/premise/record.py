"""A paper's premise record: the quantity its method exploits, on and off, and the method's paired gaps there.

Each premise notebook (03 DW-T-Loss, 05 SALAD, 07 CliqueMining) stores one record under the top-level
``"premise"`` key of its results file::

    {"quantity": "<what the method exploits>",
     "real data": {"value": <number or text>, "source": "<where it was measured or reported>"} or "not found",
     "worlds": {"on": {"value": <the quantity>, "test queries": <int>, ...},
                "off": {"value": ..., "test queries": ..., ...}},
     "comparisons": {"<method> − <baseline>": {"on": [paired per-seed differences], "off": [...]}}}

A gap is the mean of paired per-seed differences ``a_seed − b_seed``; its verdict word is recomputed from the
stored differences by the course's one rule (:mod:`vpr_nb.verdict`: a paired t test, Holm over the record's
comparisons in both worlds, one family): **helps**, **hurts** or **no measurable effect**. The notebooks print
:func:`verdict_lines`, and a test checks the stored text against the stored record.
"""
from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from .. import verdict as _verdict

WORLDS = ("on", "off")
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
    return _verdict.paired_differences(a_vals, b_vals, digits=digits)


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


def premise_verdicts(record: Mapping, gates: Mapping | None = None) -> dict[str, _verdict.Verdict]:
    """``{"<comparison>, premise <world>": Verdict}`` for every comparison and world of ``record``: one family,
    Holm-corrected over all of them (:func:`vpr_nb.verdict.verdicts`). ``gates``: ``{"<comparison>, premise
    <world>": control_gate(...)}`` where the baseline is itself fine-tuned and must pass its gate (a failed gate
    makes the comparison "inconclusive")."""
    rec = premise_record(record["quantity"], record["real data"], record["worlds"], record["comparisons"])
    return _verdict.verdicts({f"{name}, premise {w}": per[w] for name, per in rec["comparisons"].items()
                              for w in WORLDS}, gates=gates)


def verdict_lines(record: Mapping, gates: Mapping | None = None) -> list[str]:
    """One line per comparison and world, as the notebooks print them (and the consistency test reads them
    back): ``"DW-T − T-Loss, premise on: +0.036 ± 0.009 (5 seeds, t 4.1, Holm p 0.030 over 4 comparisons):
    helps"``, then the line naming the family (:func:`vpr_nb.verdict.family_note`)."""
    family = premise_verdicts(record, gates)
    return [f"{name}: {v.text()}" for name, v in family.items()] + [_verdict.family_note(family)]
