"""What moves the clique arm in CliqueMining's premise-on world (notebook 07): one probe per hypothesis, each
changing one thing in the clique arm (:mod:`vpr_nb.onoff.clique`).

With a frame every 1 m, *sparse + dense cliques* ends below *sparse + dense random* (the mining-only ablation;
``notebooks/results/07_premise.json``). Each probe below replaces the clique arm's dense half by one variant and
trains it on the same 5 seeds, world, recipe and test queries (:data:`PROBES`):

- **τ 2.5 m** -- the cliques' same-place threshold 2.5 m instead of the world's ``pos_radius`` (1.01 m).
  Hypothesis: a threshold that does not scale with the frame spacing leaves negatives 2 frames (2 m) from a
  place, as alike as its positives. Side effect (the one knob sets both): a place may span 2 m.
- **Eq. (1) uniform** -- every group descriptor equal, so Eq. (1) draws the similar clusters uniformly
  (:func:`vpr_nb.samplers.clique_batches`: all weights 0). Hypothesis: the look-alike draw is what hurts.
- **random image order** -- the clique search walks the route's images in a shuffled order, not each drawn
  cluster's frames in track order (:func:`vpr_nb.samplers.clique_batches` scans the clusters in a seeded order,
  so clique places already cover the route like random ones: :func:`route_coverage`). Hypothesis: places packed
  along the track (frames i, i+1, then i+3, i+4, ...) hurt; a shuffled order moves some negatives away
  (:func:`batch_profile`).
- **4 cliques + 4 random** -- half the dense places cliques, half random route places. Hypothesis: a clique
  batch spans little of the route (its places lie within a few similar clusters), so far places seldom meet.

Each probe is paired by seed with the premise experiment's arms (``notebooks/results/07_premise.json``, passed
to :func:`run` as ``baseline``): the probe − dense random gap says whether the variant still loses, and the probe
− cliques gap whether the change moved it. :func:`batch_profile` measures what each dense half looks like over
10 epochs (nearest other-place image, batch spread, places spanning more than the positive radius, and
:func:`route_coverage`).
"""
from __future__ import annotations

import dataclasses
from collections.abc import Mapping

import numpy as np

from .._checks import check_int
from ..losses import MultiSimilarityLoss
from ..premise.record import paired_differences
from ..recipe import RECIPE, Method, PlaceBatches
from ..recipe.arms import run_arms, test_splits
from ..samplers import CliqueBatchMaker, MixedPlaceBatches, RandomPlaceBatches
from ..synthetic import make_dataset
from . import clique as oc

WORLD = "on"
TAU = 2.5                                      # metres: no negative image within 2 frames at 1 m frames
PROBES = {
    "cliques, τ 2.5 m": "the clique threshold 2.5 m instead of the world's pos_radius (1.01 m)",
    "cliques, Eq. (1) uniform": "all group descriptors equal: Eq. (1) draws the similar clusters uniformly",
    "cliques, random image order": "the clique search walks the route's images in a shuffled order (seed 0)",
    "4 cliques + 4 random": "the dense half: 4 clique places then 4 random route places",
}
RANDOM, CLIQUES = oc.ARMS[1], oc.ARMS[2]
NEAR_NEGATIVE = 2.5                            # metres: a negative image this close is "near" in batch_profile
PROFILE_EPOCHS = 10                            # epochs of batches each dense half is profiled on

EXPERIMENT = {
    "premise experiment": "notebooks/results/07_premise.json (vpr_nb.onoff.clique): its world, arms and seeds",
    "worlds": {WORLD: oc.WORLDS[WORLD], "sparse places": oc.CITY,
               **{f"test, route seed {t['seed']}": t for t in oc.test_worlds(WORLD)[1:]}},
    "world": f"premise {WORLD}",
    "recipe": oc.R07.to_dict(),
    "probes": PROBES,
    "tau (m)": TAU,
    "paired with": [RANDOM, CLIQUES],
    "seeds": list(oc.SEEDS),
    "lr": oc.R07.lr,
}


def dense_makers(route: dict, threshold: float, route_group_descriptors) -> dict:
    """``{name: make_batches}`` of the dense half (``HALF`` places, :mod:`vpr_nb.onoff.clique`) of the two
    premise arms and of each probe, over the route training set ``route``
    (:func:`vpr_nb.onoff.clique.route_training_set`)."""
    k, half, nb = RECIPE.images_per_place, oc.HALF, oc.NB

    def cliques(places, tau=threshold, descriptors=route_group_descriptors, order=None):
        take = (lambda a: a) if order is None else (lambda a: a[order])   # noqa: E731
        maker = CliqueBatchMaker(take(route["images"]), take(route["utm"]), take(route["clusters"]), places, nb,
                                 images_per_place=k, same_place_threshold=tau, similar_groups=oc.SIMILAR_GROUPS,
                                 group_descriptors=descriptors)
        return maker if order is None else Reordered(maker, order)

    uniform = np.ones_like(np.asarray(route_group_descriptors, dtype=np.float32))
    shuffled = np.random.default_rng(0).permutation(len(route["utm"]))
    return {RANDOM: RandomPlaceBatches(route["groups"], half, k, nb, each_place_once=False),
            CLIQUES: cliques(half),
            "cliques, τ 2.5 m": cliques(half, tau=TAU),
            "cliques, Eq. (1) uniform": cliques(half, descriptors=uniform),
            "cliques, random image order": cliques(half, order=shuffled),
            "4 cliques + 4 random": MixedPlaceBatches(
                [cliques(half // 2), RandomPlaceBatches(route["groups"], half - half // 2, k, nb,
                                                        each_place_once=False)], [0, 0])}


class Reordered:
    """A place-batch maker over images taken in ``order`` (``maker`` indexes ``images[order]``), its batches
    mapped back to the original indices."""

    def __init__(self, maker, order):
        self.maker, self.order = maker, np.asarray(order, dtype=np.int64)

    def __call__(self, model, epoch: int, rng: np.random.Generator) -> np.ndarray:
        return self.order[np.asarray(self.maker(model, epoch, rng))]


def route_coverage(batches, clusters) -> dict:
    """Where a dense half's places lie along the route: the share of the route's clusters (``clusters``, one id
    per image, numbered along the track) that ``batches`` ``(B, P, K)`` use, and the share of their places in
    the first quarter of the cluster ids."""
    b, clusters = np.asarray(batches), np.asarray(clusters)
    if b.ndim != 3:
        raise ValueError(f"batches must be (batches, places, images per place), got shape {b.shape}")
    used = clusters[b[:, :, 0]].ravel()
    n = int(clusters.max()) + 1
    return {"clusters used": round(float(len(np.unique(used)) / n), 3),
            "places in the first quarter": round(float(np.mean(used < n / 4)), 3)}


def batch_profile(batches, utm, pos_radius: float) -> dict:
    """What a dense half looks like: ``batches`` ``(B, P, K)`` image indices, ``utm`` their positions. Returns
    the median distance from an image to the nearest image of another place of its batch, the share of images
    with one within :data:`NEAR_NEGATIVE` m, the median batch spread (largest distance between two images) and
    the share of a place's image pairs farther apart than ``pos_radius`` (not one place for the evaluation)."""
    b = np.asarray(batches)
    if b.ndim != 3 or b.shape[1] < 2 or b.shape[2] < 2:
        raise ValueError(f"batches must be (batches, places >= 2, images per place >= 2), got shape {b.shape}")
    u = np.asarray(utm, dtype=np.float64)[b]                                  # (B, P, K, 2)
    p, k = b.shape[1], b.shape[2]
    flat = u.reshape(len(b), p * k, 2)
    d = np.linalg.norm(flat[:, :, None] - flat[:, None], axis=-1)
    place = np.repeat(np.arange(p), k)
    same = place[:, None] == place[None]
    nearest = np.where(same, np.inf, d).min(axis=-1)
    within = np.where(same & ~np.eye(p * k, dtype=bool), d, -np.inf).reshape(len(b), p * k, p * k)
    pairs = within[within > -np.inf]
    return {"nearest other-place image (m)": round(float(np.median(nearest)), 2),
            f"images with a negative within {NEAR_NEGATIVE:g} m": round(float(np.mean(nearest < NEAR_NEGATIVE)), 3),
            "batch spread (m)": round(float(np.median(d.max(axis=(1, 2)))), 1),
            "place pairs beyond the positive radius": round(float(np.mean(pairs > pos_radius)), 3)}


def _checked_baseline(baseline, seeds) -> dict:
    if not isinstance(baseline, Mapping) or any(a not in baseline for a in (RANDOM, CLIQUES)):
        raise ValueError(f"baseline must be the premise-{WORLD} arms of notebooks/results/07_premise.json "
                         f"(results['arms']['{WORLD}']), with {RANDOM!r} and {CLIQUES!r}")
    for a in (RANDOM, CLIQUES):
        r = baseline[a].get("R@1") if isinstance(baseline[a], Mapping) else None
        if not isinstance(r, list) or len(r) != len(seeds):
            raise ValueError(f"baseline[{a!r}]['R@1'] must list one R@1 per seed ({len(seeds)}), got {r!r}")
    return {a: [float(v) for v in baseline[a]["R@1"]] for a in (RANDOM, CLIQUES)}


def run(baseline: Mapping, seeds=oc.SEEDS, workers: int = 3, max_epochs: int | None = None, select=None) -> dict:
    """Train each probe (:data:`PROBES`) in the premise-on world on ``seeds`` (as :func:`vpr_nb.onoff.clique.run`
    trains its arms) and pair it with ``baseline``, the premise-on arms of ``07_premise.json`` trained on the same
    seeds. Returns ``{"arms": {probe: run_arms arm}, "paired with": {arm: [R@1 per seed]}, "gaps": {"<probe> −
    <arm>": [paired differences]}, "batches": {dense half: batch_profile and route_coverage}}``. ``select``
    (:class:`vpr_nb.recipe.arms.Selection`): only those probes and seeds, returned as ``{"arms"}``."""
    if isinstance(seeds, (int, np.integer, str)):
        raise ValueError(f"seeds must be a list of training seeds, e.g. (0, 1, 2, 3, 4), got {seeds!r}")
    seeds = tuple(check_int(s, "seed", minimum=0) for s in seeds)
    paired = _checked_baseline(baseline, seeds)
    recipe = oc.R07 if max_epochs is None else dataclasses.replace(oc.R07, max_epochs=check_int(max_epochs,
                                                                                                "max_epochs"))
    city_train = make_dataset(oc.CITY["preset"], seed=oc.CITY["seed"], size=oc.CITY["size"], splits=("train",)).train
    ds = oc.world_splits(WORLD)
    city, route = oc.city_training_set(city_train), oc.route_training_set(ds.train)
    gdesc = oc.group_descriptors(oc.frozen_model(), route)
    dense = dense_makers(route, float(ds.train.pos_radius), gdesc)
    profile = {}
    for name, make in dense.items():           # 10 epochs of each dense half, as the first 10 epochs would mine
        b = np.concatenate([make(None, e, np.random.default_rng(e)) for e in range(PROFILE_EPOCHS)])
        profile[name] = {**batch_profile(b, route["utm"], float(ds.train.pos_radius)),
                         **route_coverage(b, route["clusters"])}
    sparse = RandomPlaceBatches(city["groups"], oc.HALF, RECIPE.images_per_place, oc.NB, each_place_once=False)
    images = np.concatenate([city["images"], route["images"]])
    offset = len(city["images"])
    methods = [Method(name, "salad", MultiSimilarityLoss(),
                      batches=PlaceBatches(name, images, MixedPlaceBatches([sparse, dense[name]], [0, offset]),
                                           (oc.HALF, oc.HALF)))
               for name in PROBES]
    tests = test_splits(oc.test_worlds(WORLD))
    found = run_arms({WORLD: {"train": ds.train, "methods": methods}}, ds.val, tests, seeds, recipe,
                     workers=check_int(workers, "workers"), lr=recipe.lr, extra=oc.arm_near_misses, select=select)
    if select is not None:
        return {"arms": found}
    arms = found[WORLD]
    gaps = {f"{p} − {a}": paired_differences(arms[p]["R@1"], paired[a]) for p in PROBES for a in (RANDOM, CLIQUES)}
    return {"arms": arms, "paired with": paired, "gaps": gaps, "batches": profile}
