"""DW-T-Loss's positive control (notebook 03): the premise at its ideal, and the step size shown directly.

**The positive control.** Eq. (4) down-weights far positives. That can only pay where a far positive is a
*wrong* one by the metric. Premise on: one positive drawn at random within 40 m, beyond the 25 m within which
evaluation counts a match, and sigma = 40 m (w = 3.9 at 5 m, 0.52 at 25 m, never negative). Negatives then
lie beyond the 40 m positive radius (:class:`vpr_nb.training.TripletSource` takes the larger radius). Premise
off, the twin: NetVLAD's best positive within 10 m at the paper's sigma = 800 m (notebook 03's premise-off
world). The four arms of :mod:`vpr_nb.onoff.dwt` train in both.

The recipe (:data:`RECIPE_CONTROL`, the premise experiment's) deviates from the course's in one way, the same
for every arm: the start is **not** a selection candidate (patience is the recipe's 6 epochs). With wrong
positives an arm may first fall and then climb, and the start as a candidate with a short patience would stop
it before it climbs.
Each arm's lr is chosen on the mean over seeds 0-2, as the course recipe does.

Wrong positives may push T-Loss below its start by design, so the protocol's gate is T-Loss beating its start
in the premise-off twin (:func:`gates`).

**The step size shown directly.** Under the paper's SGD at its lr 1e-4 (premise off), DW-T-Loss with its weight
divided by its batch mean (:class:`vpr_nb.losses.BatchMeanDWTripletLoss`: the ranking kept, the mean weight 1
like CE-Loss's) trains on the same 5 seeds as the SGD arms of ``notebooks/results/03_premise.json`` and is
paired with them (``baseline``).
"""
from __future__ import annotations

import dataclasses
from collections.abc import Mapping

import numpy as np

from ..losses import DEFAULT_EPS, BatchMeanDWTripletLoss, distance_weight
from ..premise import dwt as premise_dwt
from ..premise.record import paired_differences
from ..recipe import Method, build_start
from ..recipe.arms import run_arms
from ..verdict import control_gate
from . import dwt

WORLDS = {"on": {"positive": "random", "radius": 40.0, "sigma": 40.0},
          "off": dict(dwt.WORLDS["off"])}
SEEDS = (0, 1, 2, 3, 4)                  # the premise experiment's first 5 (its twin, run for run)
EVAL_RADIUS = 25.0                       # metres: a database image within it counts as a match at test
RECIPE_CONTROL = dwt.RECIPE_ARMS         # the premise experiment's recipe
SGD_LR = 1e-4                            # the paper's
NORMALISED = "DW-T / batch mean"
COMPARISONS = dwt.COMPARISONS
SGD_COMPARISONS = ((NORMALISED, "CE-Loss"), ("DW-T-Loss", NORMALISED), ("DW-T-Loss", "CE-Loss"))
REAL_DATA = {"value": "not measured",
             "source": "no dataset of the paper labels how wrong a far positive is; this world sets it by design"}
EXPERIMENT = {
    "train world": dwt.EXPERIMENT["train world"],
    "worlds": dwt.EXPERIMENT["worlds"],
    "premise worlds": WORLDS,
    "recipe": RECIPE_CONTROL.to_dict(),
    "arms": dwt.EXPERIMENT["arms"],
    "aggregator": "netvlad",
    "eps": DEFAULT_EPS,
    "sgd": {"world": "off", "optimizer": "sgd", "momentum": 0.9, "lr": SGD_LR, "arm": NORMALISED,
            "recipe": dwt.RECIPE_SGD.to_dict(),
            "paired with": "notebooks/results/03_premise.json, its SGD arms at the same lr"},
    "seeds": list(SEEDS),
    "premise quantity": "share of the trained-on positives farther than the 25 m evaluation radius (wrong at test)",
}


def methods(world: str) -> list[Method]:
    """The four arms of ``world`` (``"on"``: the positive control, ``"off"``: its twin)."""
    if world not in WORLDS:
        raise ValueError(f"world must be one of {sorted(WORLDS)}, got {world!r}")
    return dwt.world_methods(WORLDS[world])


def normalised_method() -> Method:
    """The SGD arm: DW-T-Loss with its weight over its batch mean, the premise-off world's positives and sigma."""
    w = WORLDS["off"]
    base = dwt.world_methods(w)[0]
    return Method(NORMALISED, "netvlad", BatchMeanDWTripletLoss(sigma=w["sigma"], eps=DEFAULT_EPS),
                  batches=base.batches)


def premise_values(train_split, seed: int = 0) -> dict:
    """The premise in each world, on the training split: the share of the positives its rule picks that lie
    beyond :data:`EVAL_RADIUS` (wrong at test), Eq. (4)'s mean weight on them and on the others, and the CV of
    the weight."""
    start = build_start(methods("off")[0], train_split, RECIPE_CONTROL, seed)
    q, db = premise_dwt.split_descriptors(train_split, start)
    out = {}
    for world, w in WORLDS.items():
        dist = np.asarray(premise_dwt.mined_positive_distances(train_split, (q, db), w["radius"], w["positive"],
                                                               seed))
        far = dist > EVAL_RADIUS
        spread = premise_dwt.weight_spread(dist, w["sigma"], DEFAULT_EPS)
        weight = distance_weight(dist, w["sigma"], DEFAULT_EPS)
        out[world] = {"value": round(float(far.mean()), 4), "positives": int(len(dist)),
                      "mean w, positives within 25 m": round(float(weight[~far].mean()), 3),
                      "mean w, positives beyond 25 m": round(float(weight[far].mean()), 3) if far.any() else None,
                      "CV of w": round(spread["cv"], 4),
                      "distance median (m)": round(float(np.median(dist)), 2)}
    return out


def gates(arms: Mapping) -> dict:
    """The protocol's gate for every comparison in both worlds (``{"<comparison>, premise <world>": Gate}``, as
    :func:`vpr_nb.premise.record.verdict_lines` takes them): T-Loss beats its start in the premise-off twin
    (with wrong positives T-Loss may end below its start by design)."""
    off = arms["off"]["T-Loss"]
    gate = control_gate(off["R@1"], off["start R@1"], "T-Loss, premise off", "its start")
    return {f"{a} − {b}, premise {w}": gate for a, b in COMPARISONS for w in WORLDS}


def run(seeds=SEEDS, workers: int = 2, max_epochs: int | None = None, select=None,
        baseline: Mapping | None = None) -> dict:
    """The reproduce profile: both worlds' arms, the premise record, and the SGD arm paired with ``baseline``
    (``{arm: {"R@1": [per seed]}}``, 03_premise.json's SGD arms at :data:`SGD_LR`, their first seeds paired with
    this run's; None: the SGD arm is left out). ``select``: only those arms and seeds, returned as ``{"arms", "sgd"}``."""
    recipe, sgd_recipe = dwt.capped(max_epochs, RECIPE_CONTROL, dwt.RECIPE_SGD)
    train, val, tests = dwt.splits()
    arms = run_arms({w: {"train": train, "methods": methods(w)} for w in WORLDS}, val, tests, seeds, recipe,
                    workers=workers, select=select)
    sgd = {}
    if baseline is not None:
        fixed = select if select is None else dataclasses.replace(select, lrs=None)
        sgd = run_arms({"off": {"train": train, "methods": [normalised_method()]}}, val, tests, seeds, sgd_recipe,
                       workers=workers, lr=SGD_LR, select=fixed).get("off", {})
        sgd = {f"{SGD_LR:g}": sgd} if sgd else {}
    if select is not None:
        return {"arms": arms, "sgd": sgd}
    record = dwt.arms_record(arms, premise_values(train), EXPERIMENT["premise quantity"], REAL_DATA)
    out = {"arms": arms, "sgd": sgd, "premise": record}
    if baseline is not None:
        n = len(sgd[f"{SGD_LR:g}"][NORMALISED]["R@1"])       # the baseline's seeds start with this run's
        if any(len(v["R@1"]) < n for v in baseline.values()):
            raise ValueError(f"the baseline needs at least this run's {n} seeds per arm (03_premise.json's SGD arms)")
        rows = {**{a: list(v["R@1"])[:n] for a, v in baseline.items()}, NORMALISED: sgd[f"{SGD_LR:g}"][NORMALISED]["R@1"]}
        out["paired with"] = {a: v for a, v in rows.items() if a != NORMALISED}
        out["sgd comparisons"] = {f"{a} − {b}": paired_differences(rows[a], rows[b]) for a, b in SGD_COMPARISONS}
    return out
