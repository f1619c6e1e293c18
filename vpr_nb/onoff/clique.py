"""CliqueMining's premise experiment (notebook 07): batches of close, look-alike places where failures are near
misses, and where they are not.

CliqueMining (Izquierdo & Civera, ECCV 2024) fills half of each batch with dense *cliques*: look-alike places
of one city just beyond the same-place threshold, so the loss sees negatives a few frames from the positive.
That can help Recall@1 only if a model's wrong top-1 retrievals are of that kind (the premise, measured by the
share of the frozen model's top-1 failures within 2 frames of the true place, :mod:`vpr_nb.premise.clique`).
The switch is the route's frame density (``camera_spacing``, :mod:`vpr_nb.synthetic.kinds.route`): the same
track and scene, notebook 07's tuned route (:data:`ROUTE`, seed 0, tiny),

- **premise on**: a frame every 1 m (``camera_spacing=1.0``; positives within 1.01 m, frames i-1, i, i+1):
  frames a few metres apart look alike, and the frozen course backbone + GeM's failures are often near
  misses (pooled over the test routes below: 0.176 within 2 frames, 0.241 within 4; 0.373 / 0.478 on route
  seed 0's own test band alone);
- **premise off**: a frame every 2.5 m, as notebook 07 trains (positives within 2.525 m): 0.040 / 0.055.

In each world notebook 07's three arms train (SALAD, one Multi-Similarity loss per half of 8 places x 4
images, 50 steps an epoch, recipe :data:`R07`: up to 40 epochs, patience 8, at the fixed ``R07.lr`` as 07
does, 5 paired seeds): **sparse only** (16 random city places), **sparse + dense random** (8 city + 8 random
route places) and **sparse + dense cliques** (8 city + 8 clique places of that world's route). Sparse places
come from city seed 0 (tiny)'s training split: 2 neighbouring spots x 1 heading quadrant; dense places are 2
consecutive frames. A clique's threshold is the world's ``pos_radius``; a cluster (what the similar-group draw,
notebook 07's Eq. (1), draws) is 10 frames in both worlds, so 10 m on and 25 m off; the group descriptors come
from the frozen course backbone + GeM, one random image per cluster, computed once.

Cliques vs sparse only is **the paper's comparison** (data and mining change together); cliques vs dense random
is **the mining-only ablation**. Each world validates on its own route's val split and tests on at least 1,000
queries, R@1 at the split's own radius (±1 frame), pooled (:func:`vpr_nb.recipe.arms.pooled_recall`) over its
own test split and the test bands of other route seeds of the same kind (:func:`test_worlds`: on, seed 0's
448 + seed 3's 1,797 = 2,245 queries; off, seed 0's 179 + seeds 3 and 4's 719 each = 1,617), 80 % of each
extra route a test split. The paper does not publish the share of near misses among failures (real data:
"not found").
"""
from __future__ import annotations

import dataclasses

import numpy as np

from .._checks import check_int
from ..evaluation import compute_descriptors
from ..losses import MultiSimilarityLoss
from ..models import build_model
from ..premise import clique as premise_clique
from ..premise.record import paired_differences, premise_record
from ..verdict import control_gate
from ..pretrain import course_backbone
from ..recipe import RECIPE, Method, PlaceBatches
from ..recipe.arms import run_arms, test_splits
from ..samplers import CliqueBatchMaker, MixedPlaceBatches, RandomPlaceBatches, sample_group_descriptors
from ..synthetic import make_dataset

ROUTE = {"num_facade_types": 60, "colour_variation": 0.3, "frame_spacing": 2.5, "frames_per_group": 2}   # 07's
WORLDS = {"on": {"preset": "route", "seed": 0, "size": "tiny", "overrides": {**ROUTE, "camera_spacing": 1.0}},
          "off": {"preset": "route", "seed": 0, "size": "tiny", "overrides": dict(ROUTE)}}
TEST_SEEDS = {"on": (3,), "off": (3, 4)}   # the fewest extra routes that bring each world to >= 1,000 test queries
TEST_FRACTIONS = (0.1, 0.1, 0.8)           # an extra route: 80 % of its frames a test split
CITY = {"preset": "city", "seed": 0, "size": "tiny"}   # the sparse places: its training split
SEEDS = (0, 1, 2, 3, 4)
HALF, NB = 8, 50                           # places per half, batches per epoch (notebook 07)
R07 = dataclasses.replace(RECIPE, max_epochs=40, patience=8)   # up to 2,000 steps, the best validation epoch kept
CITY_PLACE_SPOTS, CITY_CLUSTER_SPOTS = 2, 5   # city: a place is 2 neighbouring spots, a cluster 5 (one quadrant)
CLUSTER_PLACES = 5                         # route: a cluster is 5 places of 2 frames = 10 frames
SIMILAR_GROUPS = 15                        # Eq. (1): clusters drawn beside the anchor
ARMS = ("sparse only", "sparse + dense random", "sparse + dense cliques")
COMPARISONS = (("sparse + dense cliques", "sparse only"), ("sparse + dense cliques", "sparse + dense random"))
QUANTITY = "share of the frozen model's top-1 failures within 2 frames of the true place"
NEAR_MISS = "near-miss share"              # an arm's per-seed share of its failures within 2 frames


def _check_world(world: str) -> dict:
    if world not in WORLDS:
        raise ValueError(f"world must be one of {sorted(WORLDS)}, got {world!r}")
    return WORLDS[world]


def test_worlds(world: str) -> list[dict]:
    """The test worlds of ``world`` (``"on"`` or ``"off"``), for :func:`vpr_nb.recipe.arms.test_splits`: its own
    route's test split, then the routes of :data:`TEST_SEEDS` with the same overrides, 80 % of each a test split."""
    w = _check_world(world)
    extra = [{**w, "seed": s, "overrides": {**w["overrides"], "split_fractions": TEST_FRACTIONS}}
             for s in TEST_SEEDS[world]]
    return [dict(w), *extra]


EXPERIMENT = {
    # every world fingerprinted (vpr_nb.results): the two training worlds, the sparse places' city, the extra
    # test routes (each world's own test split is its training world's)
    "worlds": {**WORLDS, "sparse places": CITY,
               **{f"{w} test, route seed {t['seed']}": t for w in WORLDS for t in test_worlds(w)[1:]}},
    "test worlds": "each world's own test split plus the routes of seeds TEST_SEEDS[world] with the same "
                   "overrides and split_fractions (0.1, 0.1, 0.8), pooled",
    "test seeds": {w: list(s) for w, s in TEST_SEEDS.items()},
    "validation": "each world's own val split",
    "sparse places": "city seed 0 (tiny) training split: 2 spots x 1 heading quadrant",
    "recipe": R07.to_dict(),
    "arms": list(ARMS),
    "aggregator": "salad",
    "batch": {"places per half": HALF, "images_per_place": RECIPE.images_per_place, "batches_per_epoch": NB,
              "loss": "one MS loss per half (alpha 1, beta 50, miner eps 0.1), summed"},
    "clique": {"same_place_threshold": "the world's pos_radius", "similar_groups": SIMILAR_GROUPS,
               "cluster": "10 frames (10 m on, 25 m off)",
               "group descriptors": "frozen course backbone + GeM, one random image per group, computed once"},
    "lr": R07.lr,
    "seeds": list(SEEDS),
    "premise quantity": QUANTITY,
    "near miss": "top-1 wrong (beyond ±1 frame) and within 2 (or 4) frames along the track",
}


def world_splits(world: str, splits=("train", "val")):
    """The route dataset of ``world`` with ``splits`` rendered (:func:`vpr_nb.synthetic.make_dataset`)."""
    w = _check_world(world)
    return make_dataset(w["preset"], seed=w["seed"], size=w["size"], splits=splits, **w["overrides"])


def compact_ids(ids) -> np.ndarray:
    """Ids renumbered 0, 1, 2, ... in sorted order (one per element)."""
    return np.unique(np.asarray(ids), return_inverse=True)[1].reshape(-1)


def training_set(split, groups, clusters) -> dict:
    """A split's training images (database first, then queries) with their geotags, headings, place ids
    (``groups``, numbered compactly) and cluster ids (``clusters``, what Eq. (1) draws; numbered compactly)."""
    n = len(split.db_images) + len(split.q_images)
    groups, clusters = np.asarray(groups), np.asarray(clusters)
    if groups.shape != (n,) or clusters.shape != (n,):
        raise ValueError(f"groups and clusters need one id per image of the split ({n}: database, then queries), "
                         f"got shapes {groups.shape} and {clusters.shape}")
    return dict(images=np.concatenate([split.db_images, split.q_images]),
                utm=np.concatenate([split.db_utm, split.q_utm]),
                heading=np.concatenate([split.db_heading, split.q_heading]),
                groups=compact_ids(groups), clusters=compact_ids(clusters))


def _preset(split) -> str | None:
    return getattr(getattr(split, "config", None), "preset", None)


def route_training_set(split) -> dict:
    """A route split as a training set: a place is the route's group (``frames_per_group`` = 2 frames), a
    cluster :data:`CLUSTER_PLACES` places (10 frames)."""
    if _preset(split) != "route":
        raise ValueError(f"route_training_set needs a synthetic 'route' split, got {getattr(split, 'name', split)!r}")
    place = np.concatenate([split.db_place, split.q_place])
    return training_set(split, place, place // CLUSTER_PLACES)


def city_training_set(split) -> dict:
    """A city split as a training set: a place is :data:`CITY_PLACE_SPOTS` neighbouring street spots and one
    heading quadrant, a cluster :data:`CITY_CLUSTER_SPOTS` spots and one quadrant."""
    if _preset(split) != "city":
        raise ValueError(f"city_training_set needs a synthetic 'city' split, got {getattr(split, 'name', split)!r}")
    spot = np.concatenate([split.db_place, split.q_place])
    quadrant = np.floor(np.concatenate([split.db_heading, split.q_heading]) % 360 / 90).astype(np.int64)
    return training_set(split, (spot // CITY_PLACE_SPOTS) * 4 + quadrant, (spot // CITY_CLUSTER_SPOTS) * 4 + quadrant)


def frozen_model():
    """The reference and the cliques' descriptor model: the frozen course backbone + GeM."""
    return build_model(course_backbone(trainable_blocks=0), "gem")


def group_descriptors(model, data: dict, seed: int = 0) -> np.ndarray:
    """One descriptor per cluster of a training set (:func:`training_set`): that of one random image of it
    (:func:`vpr_nb.samplers.sample_group_descriptors`), computed once by ``model``."""
    seed = check_int(seed, "seed", minimum=0)
    return sample_group_descriptors(compute_descriptors(model, data["images"]), data["clusters"], seed)


def batch_makers(city: dict, route: dict, threshold: float, route_group_descriptors) -> dict:
    """``{arm: MixedPlaceBatches}`` of the three arms (:data:`ARMS`) over the images ``city`` then ``route``
    (training sets of :func:`city_training_set` and :func:`route_training_set`); ``threshold``: the cliques'
    same-place threshold in metres (the route's ``pos_radius``)."""
    k, city_n = RECIPE.images_per_place, len(city["images"])
    sparse_half = RandomPlaceBatches(city["groups"], HALF, k, NB, each_place_once=False)
    sparse_all = RandomPlaceBatches(city["groups"], 2 * HALF, k, NB, each_place_once=False)
    dense_random = RandomPlaceBatches(route["groups"], HALF, k, NB, each_place_once=False)
    dense_cliques = CliqueBatchMaker(route["images"], route["utm"], route["clusters"], HALF, NB, images_per_place=k,
                                     same_place_threshold=threshold, similar_groups=SIMILAR_GROUPS,
                                     group_descriptors=route_group_descriptors)
    return {ARMS[0]: MixedPlaceBatches([sparse_all], [0]),
            ARMS[1]: MixedPlaceBatches([sparse_half, dense_random], [0, city_n]),
            ARMS[2]: MixedPlaceBatches([sparse_half, dense_cliques], [0, city_n])}


def methods(city_train, route_train, frozen=None) -> list[Method]:
    """The three arms on ``route_train`` (a world's training split) with sparse places from ``city_train``:
    SALAD + one Multi-Similarity loss per half; the cliques' threshold is ``route_train.pos_radius`` and their
    group descriptors come from ``frozen`` (default :func:`frozen_model`)."""
    city, route = city_training_set(city_train), route_training_set(route_train)
    gdesc = group_descriptors(frozen if frozen is not None else frozen_model(), route)
    images = np.concatenate([city["images"], route["images"]])
    makers = batch_makers(city, route, float(route_train.pos_radius), gdesc)
    return [Method(name, "salad", MultiSimilarityLoss(), batches=PlaceBatches(name, images, make, (HALF, HALF)))
            for name, make in makers.items()]


def pooled_near_misses(model, tests, within=premise_clique.NEAR, *, descriptors=None) -> dict:
    """The top-1 failures of ``model`` on the test splits ``tests`` pooled: ``"queries"`` (counted), ``"failures"``,
    ``"R@1"`` and, for each k of ``within``, ``"within k frames"``: the near misses' share of all failures
    (sum over splits of near misses / sum of failures; NaN without a failure). ``descriptors``: a function
    ``images -> descriptors`` in place of ``model`` (e.g. raw pixels), as in :func:`~vpr_nb.recipe.arms.pooled_recall`."""
    if not tests:
        raise ValueError("tests must list at least one test split")
    describe = descriptors or (lambda images: compute_descriptors(model, images))
    frames, queries = [], 0
    for split in tests:
        f = premise_clique.failure_distances(describe(split.db_images), describe(split.q_images), split)
        frames.append(f.frames)
        queries += f.num_queries
    if queries == 0:
        raise ValueError("the test splits have no counted query: nothing to score")
    frames = np.concatenate(frames)
    share = premise_clique.near_miss_share(frames, within)
    return {"queries": int(queries), "failures": int(len(frames)), "R@1": float(1 - len(frames) / queries),
            **{f"within {k} frames": v for k, v in share.items()}}


def arm_near_misses(model, tests) -> dict:
    """A trained model's share of its test failures within 2 frames (:data:`NEAR_MISS`) and within 4 frames, the
    ``extra`` of :func:`vpr_nb.recipe.arms.run_arms`."""
    r = pooled_near_misses(model, tests)
    return {NEAR_MISS: r["within 2 frames"], f"{NEAR_MISS}, 4 frames": r["within 4 frames"]}


def premise_values(tests: dict, frozen=None) -> dict:
    """The premise quantity of each world: ``tests`` = ``{world: [test splits]}``; the frozen model's pooled
    near misses (:func:`pooled_near_misses`) with the frame spacing."""
    if not isinstance(tests, dict) or set(tests) - set(WORLDS) or not tests:
        raise ValueError(f"tests must be a dict {{world: [test splits]}} with worlds among {sorted(WORLDS)}")
    frozen = frozen if frozen is not None else frozen_model()
    out = {}
    for world, splits in tests.items():
        r = pooled_near_misses(frozen, splits)
        out[world] = {"value": round(r["within 2 frames"], 4), "within 4 frames": round(r["within 4 frames"], 4),
                      "failures": r["failures"], "R@1": round(r["R@1"], 4),
                      "frame spacing (m)": premise_clique.frame_spacing_of(splits[0]), "test queries": r["queries"]}
    return out


def run(seeds=SEEDS, workers: int = 3, max_epochs: int | None = None, select=None) -> dict:
    """The reproduce profile: the three arms in both worlds (``workers`` processes: one per arm), the frozen
    model's near misses, and the premise record (``max_epochs``: a shorter run, e.g. a smoke test; None: R07's).
    ``select`` (:class:`vpr_nb.recipe.arms.Selection`): only those arms and seeds, returned as ``{"arms"}``."""
    if isinstance(seeds, (int, np.integer, str)):
        raise ValueError(f"seeds must be a list of training seeds, e.g. (0, 1, 2, 3, 4), got {seeds!r}")
    seeds = tuple(check_int(s, "seed", minimum=0) for s in seeds)
    if not seeds or len(set(seeds)) != len(seeds):
        raise ValueError(f"seeds must list distinct training seeds, got {seeds}")
    workers = check_int(workers, "workers")
    recipe = R07
    if max_epochs is not None:
        recipe = dataclasses.replace(R07, max_epochs=check_int(max_epochs, "max_epochs"))
    city_train = make_dataset(CITY["preset"], seed=CITY["seed"], size=CITY["size"], splits=("train",)).train
    frozen = frozen_model()
    arms, values = {}, {}
    for world in WORLDS:
        ds = world_splits(world)
        tests = test_splits(test_worlds(world))
        spec = {world: {"train": ds.train, "methods": methods(city_train, ds.train, frozen)}}
        found = run_arms(spec, ds.val, tests, seeds, recipe, workers=workers, lr=recipe.lr,
                         extra=arm_near_misses, select=select)
        if select is not None:
            arms.update(found)
            continue
        arms[world] = found[world]
        values.update(premise_values({world: tests}, frozen))
    if select is not None:
        return {"arms": arms}
    record = premise_record(
        QUANTITY, "not found", values,
        {f"{a} − {b}": {w: paired_differences(arms[w][a]["R@1"], arms[w][b]["R@1"]) for w in WORLDS}
         for a, b in COMPARISONS})
    frozen_out = {w: {"R@1": v["R@1"], "within 2 frames": v["value"], "within 4 frames": v["within 4 frames"],
                      "failures": v["failures"], "test queries": v["test queries"]} for w, v in values.items()}
    return {"arms": arms, "premise": record, "frozen": frozen_out}


def premise_gates(results) -> dict:
    """The gates of the paper's comparison in a premise results file (``07_premise.json``'s ``results``): in each
    world, sparse only (a fine-tuned baseline) must beat the frozen backbone + GeM, else "cliques − sparse only"
    is inconclusive there (:func:`vpr_nb.premise.record.verdict_lines`' ``gates``)."""
    clique, sparse = COMPARISONS[0]
    return {f"{clique} − {sparse}, premise {w}": control_gate(results["arms"][w][sparse]["R@1"],
                                                              results["frozen"][w]["R@1"], sparse,
                                                              "frozen backbone + GeM")
            for w in WORLDS}
