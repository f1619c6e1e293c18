"""SALAD's premise experiment, made fair (notebook 05): distractors that hide place content, level starts,
each arm's lr searched, the paper's loss.

:mod:`vpr_nb.onoff.salad` could not have shown the dustbin working: its distractors covered 0.064 of the test
pixels and mostly replaced ground (place-identifying pixels fell only from 0.525 to 0.502), Sinkhorn started
0.065-0.117 below softmax, the lr was fixed, and training stopped at its epoch cap. Here:

- **premise on**: distractors (:mod:`vpr_nb.synthetic.distractors`, new at every visit, in database and
  queries) at ``distractor_rate`` 16 per 10 m, three times as tall (``distractor_height_scale`` 3: cars 3.9-5.1 m,
  people 4.5-5.7 m, so they stand in front of facades), with 4 ray hits per column of their own
  (``distractor_layers`` 4, so facades behind them never turn into sky). On city seed 2's test split: distractor
  0.382 of the pixels, object (facades, trees, poles) 0.266 against 0.525 without, sky 0.073 against 0.086
  (:func:`premise_values` measures it on every test world before training). **Premise off**: none (the
  course's worlds, exactly).
- **Level starts.** Both arms start from NetVLAD's k-means logits (``Recipe.salad_kmeans_scores``), divided by
  a temperature per arm and world (:data:`TEMPERATURES`, ``Recipe.salad_kmeans_temperature``): Sinkhorn's start
  is best at 4 (seed 0, pooled test R@1 0.400 off; 0.317 at 1); softmax at 14 starts level with it on average
  over the 5 seeds with the premise on, at 13 without (at 14 off it started 0.013 lower on average). Set on the
  starts' test R@1 (a start is not a trained result); per seed the gap still spreads by about ±0.02, since each
  seed's k-means differs (:func:`check` stores every seed's starts).
- **The paper's loss.** Multi-Similarity on P × K place batches (the recipe's 32 places × 4 images, 30 batches
  an epoch), as SALAD trains on GSV-Cities.
- **The recipe's fair test** (:data:`RECIPE_FAIR`): each arm's lr searched over the recipe's grid on the mean of
  seeds 0-2 (successive halving; the grid grows until the choice is interior), patience 6, up to 40 epochs,
  5 paired seeds. The gate: in each world softmax must beat the untrained NetVLAD-16 start of the same seed
  (:func:`netvlad_starts`).

After training, the Sinkhorn arm's dustbin: the share of each content label it sends to the dustbin on the first
64 labelled test queries, and the kept-mass AUC (object cells against uninformative ones,
:func:`vpr_nb.premise.salad.kept_mass_auc`), trained and at its start, per seed (:data:`DUSTBIN_COMPARISONS`).
"""
from __future__ import annotations

import dataclasses

from .._checks import check_int
from ..losses import MultiSimilarityLoss
from ..premise.record import paired_differences, premise_record
from ..recipe import RECIPE, VALIDATION_WORLD, Method, build_start
from ..recipe.arms import CITY_TEST_WORLDS, counted_queries, pooled_recall, run_arms
from ..verdict import control_gate, verdicts
from . import salad as os_

ON = {"distractor_rate": 16.0, "distractor_height_scale": 3.0, "distractor_layers": 4}
WORLDS = {"on": ON, "off": {}}
TEMPERATURES = {"on": {"Sinkhorn": 4.0, "softmax": 14.0}, "off": {"Sinkhorn": 4.0, "softmax": 13.0}}
SEEDS = tuple(range(8))                 # 8 paired seeds: the paper's headline comparison
CHECK_SEEDS = (0, 1, 2, 3, 4)          # the design's check before training (05_fair_check.json)
RECIPE_FAIR = dataclasses.replace(RECIPE, salad_kmeans_scores=True, max_epochs=40, search_seeds=3)
COMPARISON = ("Sinkhorn", "softmax")
GATE_REFERENCE = "untrained NetVLAD-16"
DUSTBIN_COMPARISONS = ("distractor − object, trained", "distractor − object, trained − start",
                       "kept-mass AUC, trained − start")
QUANTITY = "object (place-identifying) pixel share of the test images, database and queries of every test world"


def _with(spec: dict, overrides: dict) -> dict:
    if not overrides:
        return {k: (dict(v) if isinstance(v, dict) else v) for k, v in spec.items()}
    return {**spec, "overrides": {**dict(spec.get("overrides") or {}), **overrides}}


def world_specs(world: str) -> dict:
    """The worlds of premise ``world`` as ``make_dataset`` specs: ``{"train", "validation", "test": [...]}``."""
    if world not in WORLDS:
        raise ValueError(f"world must be one of {sorted(WORLDS)}, got {world!r}")
    o = WORLDS[world]
    return {"train": _with(os_.TRAIN_WORLD, o), "validation": _with(VALIDATION_WORLD, o),
            "test": [_with(w, o) for w in CITY_TEST_WORLDS]}


def methods(world: str = "on") -> list[tuple[Method, object]]:
    """The two arms of premise ``world`` with their recipes: SALAD from the k-means logits at the arm's
    temperature in that world, assigning by Sinkhorn + dustbin or by softmax, Multi-Similarity on place batches."""
    if world not in WORLDS:
        raise ValueError(f"world must be one of {sorted(WORLDS)}, got {world!r}")
    return [(Method(name, "salad", MultiSimilarityLoss(), batches="places", aggregator_kwargs={"assignment": a}),
             dataclasses.replace(RECIPE_FAIR, salad_kmeans_temperature=TEMPERATURES[world][name]))
            for name, a in os_.ARMS.items()]


EXPERIMENT = {
    "worlds": {f"{w} {role}": spec for w in WORLDS
               for role, spec in [("train", world_specs(w)["train"]), ("validation", world_specs(w)["validation"]),
                                  *((f"test, city seed {t['seed']}", t) for t in world_specs(w)["test"])]},
    "premise worlds": WORLDS,
    "recipe": RECIPE_FAIR.to_dict(),
    "temperatures": TEMPERATURES,
    "arms": [m.to_dict() for m, _ in methods("on")],
    "aggregator": "salad",
    "loss": "Multi-Similarity on P x K place batches",
    "seeds": list(SEEDS),
    "gate": f"softmax beats the {GATE_REFERENCE} start of the same seed (one-sided paired t test)",
    "premise quantity": QUANTITY,
    "dustbin": {**os_.EXPERIMENT["dustbin"], "comparisons": list(DUSTBIN_COMPARISONS)},
}
CHECK_EXPERIMENT = {**EXPERIMENT, "seeds": list(CHECK_SEEDS)}   # what :func:`check` ran with


def world_splits(world: str) -> tuple:
    """``(train, val, tests)`` of premise ``world``; the test splits rendered with content labels."""
    specs = world_specs(world)
    return (os_._render(specs["train"], "train", False), os_._render(specs["validation"], "val", False),
            [os_._render(t, "test", True) for t in specs["test"]])


def premise_values(tests) -> dict:
    """Every label's pixel share on the test splits; ``"value"`` the object share."""
    v = os_.premise_values(tests)
    return {"value": v["label shares"]["object"], "distractor share": v["value"],
            "distractor share, database": v["distractor share, database"],
            "distractor share, queries": v["distractor share, queries"], "label shares": v["label shares"]}


def netvlad_starts(train, tests, seeds) -> list[float]:
    """The untrained NetVLAD-16 start of each seed (the recipe's k-means start), pooled test R@1."""
    m = Method("NetVLAD-16 start", "netvlad")
    return [round(pooled_recall(build_start(m, train, RECIPE_FAIR, s), tests, RECIPE.ns)[RECIPE.ns[0]], 4)
            for s in seeds]


def start_dustbin(train, sample, seeds, world: str = "on") -> dict:
    """The Sinkhorn arm's start per seed: ``{key: [per seed]}`` of :func:`vpr_nb.onoff.salad.dustbin_values`."""
    method, recipe = methods(world)[0]
    rows = [os_.dustbin_values(build_start(method, train, recipe, s), *sample) for s in seeds]
    return {k: [round(float(r[k]), 4) for r in rows] for k in rows[0]}


def dustbin_comparisons(trained: dict, start: dict) -> dict:
    """Per-seed differences of :data:`DUSTBIN_COMPARISONS` from the trained and start dustbin values (a world
    without distractors: the AUC's alone)."""
    d, o = os_.SHARE.format("distractor"), os_.SHARE.format("object")
    out = {}
    if d in trained and d in start:
        gap_t = [a - b for a, b in zip(trained[d], trained[o])]
        gap_s = [a - b for a, b in zip(start[d], start[o])]
        out = {DUSTBIN_COMPARISONS[0]: [round(x, 4) for x in gap_t],
               DUSTBIN_COMPARISONS[1]: paired_differences(gap_t, gap_s)}
    return {**out, DUSTBIN_COMPARISONS[2]: paired_differences(trained[os_.AUC], start[os_.AUC])}


def gates(results) -> dict:
    """Each world's gate: softmax beats the untrained NetVLAD-16 start of the same seed."""
    a, b = COMPARISON
    return {f"{a} − {b}, premise {w}": control_gate(results["arms"][w][b]["R@1"], results["netvlad start"][w],
                                                     b, GATE_REFERENCE) for w in WORLDS}


def dustbin_verdicts(results) -> dict:
    """The dustbin table of a results file's ``results``, one Holm family: ``{"<comparison>, premise <world>":
    Verdict}`` over each world's :data:`DUSTBIN_COMPARISONS` (per-seed differences; "helps": the dustbin takes
    more of a distractor cell than of an object cell, or ranks object cells higher, than its reference)."""
    return verdicts({f"{name}, premise {w}": d for w in WORLDS
                     for name, d in results["dustbin"][w]["comparisons"].items()})


def arm_starts(train, tests, seeds, world: str = "on") -> dict:
    """Each arm's start (its temperature, :func:`methods`) of every seed, pooled test R@1: ``{arm: [per seed]}``."""
    return {m.name: [round(pooled_recall(build_start(m, train, r, s), tests, RECIPE.ns)[RECIPE.ns[0]], 4)
                     for s in seeds] for m, r in methods(world)}


def check(seeds=CHECK_SEEDS) -> dict:
    """The design, checked before any training (``notebooks/results/05_fair_check.json``): each world's label
    shares on its test worlds, both arms' starts and the untrained NetVLAD-16 of every seed, and the Sinkhorn
    start's dustbin per label. Cheap (no fine-tune): the premise and the level starts hold or not before a
    run spends its hours."""
    seeds = os_._check_seeds(seeds)
    out = {"premise": {}, "start R@1": {}, "netvlad start": {}, "start dustbin": {}}
    for world in WORLDS:
        train, _val, tests = world_splits(world)
        out["premise"][world] = {**premise_values(tests), "test queries": sum(counted_queries(t) for t in tests)}
        out["start R@1"][world] = arm_starts(train, tests, seeds, world)
        out["netvlad start"][world] = netvlad_starts(train, tests, seeds)
        out["start dustbin"][world] = start_dustbin(train, os_.labelled_sample(tests), seeds, world)
    return out


def run(seeds=SEEDS, workers: int = 2, max_epochs: int | None = None, select=None) -> dict:
    """The reproduce profile: both arms in both worlds, the NetVLAD-16 starts, the premise record and the
    dustbin's measurement. ``select``: only those arms and seeds, returned as ``{"arms"}``."""
    seeds = os_._check_seeds(seeds)
    workers = check_int(workers, "workers")
    if max_epochs is not None:
        check_int(max_epochs, "max_epochs")
    arms, values, nv, dustbin = {}, {}, {}, {}
    for world in WORLDS:
        arm_methods = [(m, r if max_epochs is None else dataclasses.replace(r, max_epochs=max_epochs))
                       for m, r in methods(world)]
        train, val, tests = world_splits(world)
        sample = os_.labelled_sample(tests)
        found = run_arms({world: {"train": train, "methods": arm_methods}}, val, tests, seeds, RECIPE_FAIR,
                         workers=workers, select=select,
                         extra=lambda model, _tests, s=sample: os_.dustbin_values(model, *s))
        if select is not None:
            arms.update(found)
            continue
        arms[world] = found[world]
        nv[world] = netvlad_starts(train, tests, seeds)
        values[world] = {**premise_values(tests), "test queries": found[world][COMPARISON[0]]["test queries"]}
        trained = found[world][COMPARISON[0]]
        start = start_dustbin(train, sample, seeds, world)
        dustbin[world] = {"start": start, "comparisons": dustbin_comparisons(trained, start)}
    if select is not None:
        return {"arms": arms}
    a, b = COMPARISON
    record = premise_record(QUANTITY, "not found", values,
                            {f"{a} − {b}": {w: paired_differences(arms[w][a]["R@1"], arms[w][b]["R@1"])
                                            for w in WORLDS}})
    return {"arms": arms, "netvlad start": nv, "premise": record, "dustbin": dustbin}
