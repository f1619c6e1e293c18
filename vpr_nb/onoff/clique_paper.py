"""CliqueMining's own comparison, gated (notebook 07): sparse + dense cliques against sparse places only, with a
sparse baseline that can beat the frozen reference.

In :mod:`vpr_nb.onoff.clique` the paper's comparison is inconclusive: *sparse only* trains a SALAD head from
scratch on city places and is tested on the route, so it starts at 0.32 R@1 against the frozen backbone + GeM's
0.78 and ends below the frozen model. Here the three arms differ only in their batches:

- **one head, one start.** Every arm is the course backbone + GeM, whose start *is* the frozen reference
  (:func:`vpr_nb.onoff.clique.frozen_model`), its last block trained at a searched lr (the recipe's grid on the
  mean of seeds 0-2, grown until the choice is interior);
- **sparse places from the route.** As GSV-Cities' places lie far apart, the sparse places are the route's own
  places (2 consecutive frames) one every :data:`SPARSE_STRIDE` places (:data:`SPARSE_SPACING_M` metres of
  track), so a sparse batch has no close negative; the dense half (random or cliques) draws from every place;
- **the world where near misses dominate** (:mod:`vpr_nb.onoff.clique_nearmiss`: a frame every 0.25 m, 0.603 of
  the frozen model's failures within 4 frames), its own val split to select on and its 1,797 test queries.

Arms (one Multi-Similarity loss per half of 8 places x 4 images, 50 batches an epoch, recipe
:data:`vpr_nb.onoff.clique.R07`): **sparse only** (both halves sparse), **sparse + dense random** and **sparse +
dense cliques** (the first half sparse). 8 paired seeds. The gate: sparse only beats the frozen model (its start).
Cliques − sparse only is the paper's comparison (data and mining change together), cliques − dense random the
mining-only ablation; one Holm family of two.
"""
from __future__ import annotations

import dataclasses

import numpy as np

from .._checks import check_int
from ..losses import MultiSimilarityLoss
from ..recipe import RECIPE, Method, PlaceBatches
from ..recipe.arms import run_arms
from ..samplers import CliqueBatchMaker, MixedPlaceBatches, RandomPlaceBatches
from ..verdict import control_gate, verdicts
from . import clique as oc
from . import clique_nearmiss as nm

SPARSE_SPACING_M = 25.0                       # metres of track between two sparse places
SPARSE_STRIDE = round(SPARSE_SPACING_M / (nm.WORLD["overrides"]["camera_spacing"]
                                          * nm.WORLD["overrides"]["frames_per_group"]))   # places: 50
SEEDS = tuple(range(8))
ARMS = ("sparse only", "sparse + dense random", "sparse + dense cliques")
COMPARISONS = (("sparse + dense cliques", "sparse only"), ("sparse + dense cliques", "sparse + dense random"))
REFERENCE = "frozen backbone + GeM"
EXPERIMENT = {
    "worlds": {"near misses": nm.WORLD},
    "validation": "the world's own val split", "test": "the world's own test split",
    "near miss": nm.EXPERIMENT["near miss"],
    "recipe": oc.R07.to_dict(),
    "arms": list(ARMS),
    "aggregator": "gem, from the frozen reference (the course backbone's last block trained)",
    "sparse places": f"the route's places, one every {SPARSE_STRIDE} ({SPARSE_SPACING_M:g} m of track)",
    "batch": oc.EXPERIMENT["batch"],
    "clique": {**oc.EXPERIMENT["clique"], "cluster": "10 frames (2.5 m)"},
    "lr": "searched per arm on seeds 0-2 (the recipe's grid, grown until interior)",
    "seeds": list(SEEDS),
    "comparisons": [f"{a} − {b}" for a, b in COMPARISONS],
    "gate": f"sparse only beats the {REFERENCE} (one-sided paired t test)",
}


def sparse_subset(route: dict, stride: int = SPARSE_STRIDE) -> dict:
    """The places of a route training set (:func:`vpr_nb.onoff.clique.route_training_set`) whose id is a
    multiple of ``stride``, as a training set of their own (place and cluster ids renumbered compactly)."""
    stride = check_int(stride, "stride")
    keep = route["groups"] % stride == 0
    if len(np.unique(route["groups"][keep])) < 2 * oc.HALF:
        raise ValueError(f"one place in {stride} leaves {len(np.unique(route['groups'][keep]))} sparse places, "
                         f"fewer than a sparse-only batch's {2 * oc.HALF}; lower the stride")
    return {**{k: v[keep] for k, v in route.items()}, "groups": oc.compact_ids(route["groups"][keep]),
            "clusters": oc.compact_ids(route["clusters"][keep])}


def methods(route_train, frozen=None, head: str = "gem") -> list[Method]:
    """The three arms (:data:`ARMS`) on ``route_train``: ``head`` (every arm the same aggregator), one
    Multi-Similarity loss per half, sparse places from :func:`sparse_subset`; the cliques' threshold is
    ``route_train.pos_radius`` and their group descriptors come from ``frozen`` (default
    :func:`vpr_nb.onoff.clique.frozen_model`)."""
    route = oc.route_training_set(route_train)
    sparse = sparse_subset(route)
    gdesc = oc.group_descriptors(frozen if frozen is not None else oc.frozen_model(), route)
    k, half, nb, n = RECIPE.images_per_place, oc.HALF, oc.NB, len(sparse["images"])
    sparse_half = RandomPlaceBatches(sparse["groups"], half, k, nb, each_place_once=False)
    makers = {
        ARMS[0]: MixedPlaceBatches([RandomPlaceBatches(sparse["groups"], 2 * half, k, nb, each_place_once=False)],
                                   [0]),
        ARMS[1]: MixedPlaceBatches([sparse_half, RandomPlaceBatches(route["groups"], half, k, nb,
                                                                    each_place_once=False)], [0, n]),
        ARMS[2]: MixedPlaceBatches([sparse_half, CliqueBatchMaker(
            route["images"], route["utm"], route["clusters"], half, nb, images_per_place=k,
            same_place_threshold=float(route_train.pos_radius), similar_groups=oc.SIMILAR_GROUPS,
            group_descriptors=gdesc)], [0, n])}
    images = np.concatenate([sparse["images"], route["images"]])
    return [Method(name, head, MultiSimilarityLoss(), batches=PlaceBatches(name, images, make, (half, half)))
            for name, make in makers.items()]


def run(seeds=SEEDS, workers: int = 2, max_epochs: int | None = None, select=None, head: str = "gem") -> dict:
    """The reproduce profile: the frozen model's failures, then the three arms on ``seeds``, each arm's lr
    searched. ``select`` (:class:`vpr_nb.recipe.arms.Selection`): only those arms and seeds, as ``{"arms"}``.
    ``head``: the aggregator of every arm (:mod:`vpr_nb.onoff.clique_paper_salad`: SALAD)."""
    seeds = tuple(check_int(s, "seed", minimum=0) for s in seeds)
    recipe = oc.R07 if max_epochs is None else dataclasses.replace(oc.R07, max_epochs=check_int(max_epochs,
                                                                                                "max_epochs"))
    frozen = oc.frozen_model()
    ds = nm.world_splits()
    found = run_arms({"near misses": {"train": ds.train, "methods": methods(ds.train, frozen, head)}}, ds.val,
                     [ds.test], seeds, recipe, workers=workers, extra=nm._near_misses, select=select)
    if select is not None:
        return {"arms": found}
    arms = found["near misses"]
    return {"frozen": nm.premise_values(ds.test, frozen), "arms": arms,
            "comparisons": {f"{a} − {b}": [round(x - y, 4) for x, y in zip(arms[a]["R@1"], arms[b]["R@1"])]
                            for a, b in COMPARISONS}}


def gate(results):
    """The gate of the paper's comparison in a results file's ``results``: sparse only beats the frozen model."""
    return control_gate(results["arms"][ARMS[0]]["R@1"], results["frozen"]["R@1"], ARMS[0], REFERENCE)


def verdicts_of(results) -> dict:
    """Both comparisons' verdicts, one Holm family; the paper's comparison gated by :func:`gate`."""
    name = f"{COMPARISONS[0][0]} − {COMPARISONS[0][1]}"
    return verdicts(results["comparisons"], gates={name: gate(results)})

