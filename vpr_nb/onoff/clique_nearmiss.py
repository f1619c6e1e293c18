"""CliqueMining where near misses dominate (notebook 07): the mining-only ablation in a world whose frozen
model fails mostly a few frames from the true place.

In the premise-on world of :mod:`vpr_nb.onoff.clique` (a frame every 1 m) the frozen course backbone + GeM
fails on 0.218 of the test queries, and 0.241 of those failures lie within 4 frames of the true place: no
near-miss fix could gain more than about 0.05 R@1 there (failure rate × near-miss share, the **ceiling**).
This world packs the frames four times closer: the same track and scene (notebook 07's route, seed 0, tiny),
a frame every 0.25 m (``camera_spacing=0.25``; positives within 0.2525 m, frames i-1, i, i+1).

**Near miss** here: a top-1 failure (the retrieved image lies beyond ±1 frame of the query) whose retrieved
image lies within 4 frames (1 m) along the track of the query's true place. The share of near misses among
the frozen model's failures on the test split is measured before any training (:func:`premise_values`), with
the ceiling; the course's 2-frame share is reported beside it.

Two arms of :mod:`vpr_nb.onoff.clique` train as there (SALAD, one Multi-Similarity loss per half, recipe
:data:`vpr_nb.onoff.clique.R07` at its fixed lr, sparse city places in the first half): **sparse + dense random**
and **sparse + dense cliques** (the clique search scans the drawn clusters in a seeded order, so clique places
cover the route like random ones). Cliques' same-place threshold is this world's ``pos_radius`` and a cluster is
10 frames (2.5 m). The test split is the route's own (1,797 queries); validation its own val split.

The comparison, cliques − dense random, is gated: dense random must beat the frozen backbone + GeM.
"""
from __future__ import annotations

import dataclasses

from .._checks import check_int
from ..recipe.arms import run_arms
from ..synthetic import make_dataset
from ..verdict import control_gate, verdicts
from . import clique as oc

WORLD = {"preset": "route", "seed": 0, "size": "tiny", "overrides": {**oc.ROUTE, "camera_spacing": 0.25}}
NEAR_FRAMES = 4                       # a near miss: within this many frames of the true place
SEEDS = (0, 1, 2, 3, 4, 5, 6, 7)
ARMS = (oc.ARMS[1], oc.ARMS[2])       # sparse + dense random, sparse + dense cliques
COMPARISON = f"{ARMS[1]} − {ARMS[0]}"
EXPERIMENT = {
    "worlds": {"near misses": WORLD, "sparse places": oc.CITY},
    "validation": "the world's own val split", "test": "the world's own test split",
    "near miss": f"top-1 wrong (beyond ±1 frame) and within {NEAR_FRAMES} frames "
                 f"({NEAR_FRAMES * WORLD['overrides']['camera_spacing']:g} m) along the track",
    "recipe": oc.R07.to_dict(),
    "arms": list(ARMS),
    "batch": oc.EXPERIMENT["batch"],
    "clique": {**oc.EXPERIMENT["clique"], "cluster": "10 frames (2.5 m)"},
    "lr": oc.R07.lr,
    "seeds": list(SEEDS),
    "gate": "sparse + dense random beats the frozen backbone + GeM (one-sided paired t test)",
}


def world_splits(splits=("train", "val", "test")):
    """The near-miss world's route with ``splits`` rendered."""
    return make_dataset(WORLD["preset"], seed=WORLD["seed"], size=WORLD["size"], splits=splits, **WORLD["overrides"])


def premise_values(test, frozen=None) -> dict:
    """The frozen model's failures on ``test``: R@1, the near-miss shares within 2 and :data:`NEAR_FRAMES`
    frames, and the ceiling (failure rate × near-miss share: the most R@1 a model that fixed every near miss
    and changed nothing else could gain)."""
    r = oc.pooled_near_misses(frozen if frozen is not None else oc.frozen_model(), [test], within=(2, NEAR_FRAMES))
    share = r[f"within {NEAR_FRAMES} frames"]
    return {"R@1": round(r["R@1"], 4), "failures": r["failures"], "test queries": r["queries"],
            "within 2 frames": round(r["within 2 frames"], 4), f"within {NEAR_FRAMES} frames": round(share, 4),
            "ceiling (R@1)": round((1 - r["R@1"]) * share, 4),
            "frame spacing (m)": WORLD["overrides"]["camera_spacing"]}


def gate(results):
    """The gate of the comparison in a results file's ``results``: dense random beats the frozen model."""
    arm = results["arms"][ARMS[0]]
    return control_gate(arm["R@1"], results["frozen"]["R@1"], ARMS[0], "frozen backbone + GeM")


def verdict_of(results):
    """The comparison's verdict (one comparison: its own family), gated by :func:`gate`."""
    return verdicts({COMPARISON: results["comparisons"][COMPARISON]}, gates={COMPARISON: gate(results)})[COMPARISON]


def run(seeds=SEEDS, workers: int = 2, max_epochs: int | None = None, select=None) -> dict:
    """The reproduce profile: the frozen model's failures, then both arms on ``seeds``. ``select``
    (:class:`vpr_nb.recipe.arms.Selection`): only those arms and seeds, returned as ``{"arms"}``."""
    seeds = tuple(check_int(s, "seed", minimum=0) for s in seeds)
    recipe = oc.R07 if max_epochs is None else dataclasses.replace(oc.R07, max_epochs=check_int(max_epochs,
                                                                                                "max_epochs"))
    city_train = make_dataset(oc.CITY["preset"], seed=oc.CITY["seed"], size=oc.CITY["size"], splits=("train",)).train
    frozen = oc.frozen_model()
    ds = world_splits()
    methods = [m for m in oc.methods(city_train, ds.train, frozen) if m.name in ARMS]
    found = run_arms({"near misses": {"train": ds.train, "methods": methods}}, ds.val, [ds.test], seeds, recipe,
                     workers=workers, lr=recipe.lr, extra=_near_misses, select=select)
    if select is not None:
        return {"arms": found}
    arms = found["near misses"]
    out = {"frozen": premise_values(ds.test, frozen), "arms": arms,
           "comparisons": {COMPARISON: [round(a - b, 4) for a, b in zip(arms[ARMS[1]]["R@1"], arms[ARMS[0]]["R@1"])]}}
    return out


def _near_misses(model, tests) -> dict:
    r = oc.pooled_near_misses(model, tests, within=(2, NEAR_FRAMES))
    return {"near-miss share": r[f"within {NEAR_FRAMES} frames"], "near-miss share, 2 frames": r["within 2 frames"]}
