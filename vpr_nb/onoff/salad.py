"""SALAD's premise experiment (notebook 05): a dustbin where local features come and go between visits, and
where none do.

SALAD (Izquierdo & Civera, CVPR 2024, "Optimal Transport Aggregation for Visual Place Recognition") assigns the
n local features of an image to m clusters by optimal transport (notebook 05's Eq. (1)), solved by 3 Sinkhorn
iterations (Eq. (2)) on the scores augmented with a dustbin row, under the marginals of Eq. (3): each feature
gives 1, each cluster receives 1, the dustbin the other n − m. The descriptor sums the features under the plan
without its dustbin row (Eqs. (4)-(5)). The premise: the dustbin discards what does not identify the place.
Two facts frame it. By Eq. (3)'s marginals the dustbin receives (n − m)/n of the mass by construction
(0.833 for the course's 8 × 12 feature map, n = 96, and m = 16 clusters), whatever the scores; and its one
learned scalar cancels in Eq. (2)'s row update (u first, as in the published code), so the plan does not
depend on it. Only the score head chooses *which* features go there. (The marginals hold at Sinkhorn's
convergence: with SALAD's 3 iterations and the sharp k-means scores below, the clusters receive about half
their unit of mass and the dustbin 0.91 on average, measured on the start of seed 0; 0.847 after 20
iterations, 0.833 after 100; the recipe's near-uniform start gives 0.833 at once. :data:`MEAN` records it.)

The switch is content that differs between visits of a place (``WorldConfig.distractor_rate``,
:mod:`vpr_nb.synthetic.distractors`: parked cars and pedestrians in 3-D, new at every visit, in the database
and in the queries alike):

- **premise on**: :data:`DISTRACTOR_RATE` = 4 per 10 m of street: distractors cover 0.060 of the database
  pixels and 0.070 of the query pixels of the two test worlds (0.064 of all). On city seed 2's test split,
  database / queries: rate 2 gives 0.034 / 0.040, rate 4 0.057 / 0.071, rate 8 0.097 / 0.113, but where
  several distractors stand in one column the ray caster's 4 hit layers run out and the facade behind them
  turns to sky and skyline: +0.024 of the pixels at rate 8, +0.007 at 4, +0.002 at 2 (measured against 8
  layers), so rate 4 is the compromise;
- **premise off**: none (rate 0: today's worlds, exactly). Both worlds keep the queries' image-space occluders
  (``occluder_rate``), 0.027 of the query pixels.

Training (city seed 0, tiny), validation (:data:`vpr_nb.recipe.VALIDATION_WORLD`) and test worlds
(:data:`vpr_nb.recipe.arms.CITY_TEST_WORLDS`, 1,749 test queries pooled) all get the world's rate. In each
world two arms train, the mechanism's ablation from one start: the recipe's SALAD head (16 clusters × 32 + a
64-D token, standardised inputs) with its score head set to NetVLAD's k-means logits
(``Recipe.salad_kmeans_scores``, :func:`vpr_nb.models.init_salad_scores_from_kmeans`; the same weights in both
arms), assigning by

- **Sinkhorn**: the plan of Eqs. (2)-(3) with the dustbin (``SALAD(assignment="sinkhorn")``, the paper's);
- **softmax**: ``P = softmax_k(s)`` in place of Eqs. (2)-(3) in Eq. (4), each feature's unit of mass over the
  clusters alone, NetVLAD's way: no dustbin, no cluster marginal (``assignment="softmax"``).

One start is not one recall: on the same weights the assignment alone moves the start's test R@1 (seed 0:
Sinkhorn 0.317, softmax 0.440 off; 0.210 and 0.288 on).

Both train as notebook 05 trains its SALAD row (the recipe's triplet batches and triplet loss, at the recipe's
fixed lr), 5 paired seeds, test R@1 pooled. Beside it, what the trained Sinkhorn arm's
dustbin takes per content label and how well its kept mass tells ``object`` cells from uninformative ones
(:mod:`vpr_nb.premise.salad`), on the first :data:`LABELLED_IMAGES` test queries of the first test world.

The arms share their start weights; :func:`run` scores each arm's start with its own assignment and measures
its dustbin (:func:`start_values`).
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np

from .._checks import check_int
from ..premise import salad as premise_salad
from ..premise.record import paired_differences, premise_record
from ..recipe import RECIPE, VALIDATION_WORLD, Method, build_start
from ..recipe.arms import CITY_TEST_WORLDS, pooled_recall, run_arms
from ..synthetic import LABEL_NAMES, make_dataset

DISTRACTOR_RATE = 4.0                      # distractors per 10 m of street, premise on
RATES = {"on": DISTRACTOR_RATE, "off": 0.0}
TRAIN_WORLD = {"preset": "city", "seed": 0, "size": "tiny"}
SEEDS = (0, 1, 2, 3, 4)
ARMS = {"Sinkhorn": "sinkhorn", "softmax": "softmax"}          # arm name: SALAD's assignment
COMPARISON = ("Sinkhorn", "softmax")
RECIPE_ARMS = dataclasses.replace(RECIPE, search_seeds=1, salad_kmeans_scores=True)
LABELLED_IMAGES = 64                       # the dustbin's measurement: the first 64 test queries of the first
                                           # test world, rendered with content labels
QUANTITY = "distractor pixel share of the test images (database and queries of every test world)"
REAL_DATA = "not found"   # premises.md: vehicles + people 0.05-0.10 of street-level pixels is a guess, unsourced
AUC = "kept-mass AUC"                      # per-seed key of the Sinkhorn arm (premise.salad.kept_mass_auc)
SHARE = "dustbin share, {}"                # per-seed key of the Sinkhorn arm, one per content label
MEAN = "dustbin share, all cells"          # per-seed key of the Sinkhorn arm: the mean over every cell


def _check_world(world: str) -> str:
    if world not in RATES:
        raise ValueError(f"world must be one of {sorted(RATES)}, got {world!r}")
    return world


def _with_rate(spec: dict, rate: float) -> dict:
    """``spec`` with ``distractor_rate`` added to its overrides (rate 0: ``spec`` unchanged, today's world)."""
    if rate == 0:
        return {k: (dict(v) if isinstance(v, dict) else v) for k, v in spec.items()}
    return {**spec, "overrides": {**dict(spec.get("overrides") or {}), "distractor_rate": float(rate)}}


def world_specs(world: str) -> dict:
    """The worlds of premise ``world`` (``"on"`` or ``"off"``) as ``make_dataset`` specs (``preset``, ``seed``,
    ``size``, ``overrides``): ``{"train": spec, "validation": spec, "test": [specs]}``, each the course's world
    with the world's distractor rate (``"off"``: the course's worlds as they are)."""
    rate = RATES[_check_world(world)]
    return {"train": _with_rate(TRAIN_WORLD, rate), "validation": _with_rate(VALIDATION_WORLD, rate),
            "test": [_with_rate(w, rate) for w in CITY_TEST_WORLDS]}


def methods() -> list[Method]:
    """The two arms (the same in both worlds): the recipe's SALAD with Sinkhorn + dustbin and with softmax,
    triplet batches and the recipe's triplet loss, as notebook 05's SALAD row."""
    return [Method(name, "salad", aggregator_kwargs={"assignment": a}) for name, a in ARMS.items()]


EXPERIMENT = {
    # every world fingerprinted (vpr_nb.results): training, validation and test worlds of both premise worlds
    "worlds": {f"{w} {role}": spec for w in RATES
               for role, spec in [("train", world_specs(w)["train"]), ("validation", world_specs(w)["validation"]),
                                  *((f"test, city seed {t['seed']}", t) for t in world_specs(w)["test"])]},
    "premise worlds": {w: {"distractor_rate": r} for w, r in RATES.items()},
    "recipe": RECIPE_ARMS.to_dict(),
    "arms": [m.to_dict() for m in methods()],
    "aggregator": "salad",
    "start": "standardised head inputs and the score head from NetVLAD's k-means logits (recipe.salad_kmeans_scores)",
    "batches": "triplets with the recipe's triplet loss (notebook 05's SALAD row)",
    "lr": "fixed, the recipe's lr, as notebook 05 trains its SALAD rows",
    "seeds": list(SEEDS),
    "premise quantity": QUANTITY,
    "dustbin": {"images": f"the first {LABELLED_IMAGES} test queries of the first test world, labelled",
                "informative": list(premise_salad.INFORMATIVE), "uninformative": list(premise_salad.UNINFORMATIVE),
                "arm": "Sinkhorn"},
}


def _render(spec: dict, split: str, labels: bool):
    return getattr(make_dataset(spec["preset"], seed=spec["seed"], size=spec.get("size", "tiny"), splits=(split,),
                                labels=labels, **dict(spec.get("overrides") or {})), split)


def world_splits(world: str) -> tuple:
    """``(train, val, tests)`` of premise ``world``: the training split, the validation split and the test
    splits (rendered with content labels, ``db_labels`` / ``q_labels``) of :func:`world_specs`."""
    specs = world_specs(world)
    return (_render(specs["train"], "train", False), _render(specs["validation"], "val", False),
            [_render(t, "test", True) for t in specs["test"]])


def labelled_sample(tests, n: int = LABELLED_IMAGES) -> tuple[np.ndarray, np.ndarray]:
    """The first ``n`` queries of the first test split and their content labels: ``(images, labels)``."""
    n = check_int(n, "n")
    if not tests or getattr(tests[0], "q_labels", None) is None:
        raise ValueError("tests must start with a test split rendered with labels "
                         "(make_dataset(..., labels=True), as world_splits renders them)")
    return tests[0].q_images[:n], tests[0].q_labels[:n]


def dustbin_values(model, images, labels) -> dict:
    """What a SALAD with Sinkhorn's dustbin takes on ``images`` (uint8 (N, H, W, 3)) with content ``labels``
    (N, H, W): the mean dustbin share per content label (``"dustbin share, <label>"``; labels no cell has are
    left out), over every cell (:data:`MEAN`) and :data:`AUC`, how well the kept mass tells ``object`` cells
    from uninformative ones (:mod:`vpr_nb.premise.salad`). A model that assigns by softmax has no dustbin:
    ``{}``."""
    if getattr(getattr(model, "aggregator", None), "assignment", None) == "softmax":
        return {}
    shares = premise_salad.dustbin_shares(model, images)
    per_label = premise_salad.share_by_label(shares, labels)
    return {**{SHARE.format(k): v for k, v in per_label.items() if not math.isnan(v)},
            MEAN: float(shares.mean()), AUC: premise_salad.kept_mass_auc(shares, labels)}


def premise_values(tests) -> dict:
    """The premise quantity on the test splits ``tests`` (rendered with labels): ``"value"``, the distractor
    share of all their pixels (database and queries), beside the share in each and every label's share."""
    if not tests or any(getattr(s, "q_labels", None) is None or s.db_labels is None for s in tests):
        raise ValueError("tests must be test splits rendered with labels (make_dataset(..., labels=True))")
    db = np.concatenate([s.db_labels for s in tests])
    q = np.concatenate([s.q_labels for s in tests])
    both = premise_salad.label_shares(np.concatenate([db, q]))
    return {"value": round(both["distractor"], 4),
            "distractor share, database": round(premise_salad.label_shares(db)["distractor"], 4),
            "distractor share, queries": round(premise_salad.label_shares(q)["distractor"], 4),
            "label shares": {k: round(v, 4) for k, v in both.items()}}


def start_values(train_split, tests, seeds, recipe=RECIPE_ARMS, sample=None, digits: int = 4) -> dict:
    """Each arm's start scored on ``tests`` (:func:`pooled_recall`), per seed: ``{"start R@1": {arm: [...]},
    "dustbin": <dustbin_values of the first seed's Sinkhorn start on sample = (images, labels)> or None,
    "dustbin mass": (n − m) / n}`` (Eq. (3): n feature positions, m clusters). run_arms scores a set of start
    weights once, and both arms start from the same weights."""
    seeds = _check_seeds(seeds)
    out, dustbin, mass = {name: [] for name in ARMS}, None, None
    for seed in seeds:
        for method in methods():
            start = build_start(method, train_split, recipe, seed)
            out[method.name].append(round(pooled_recall(start, tests, recipe.ns)[recipe.ns[0]], digits))
            if sample is not None and seed == seeds[0] and ARMS[method.name] == "sinkhorn":
                dustbin = dustbin_values(start, *sample)
                n = math.prod(d // start.backbone.stride for d in np.shape(sample[0])[1:3])
                mass = (n - start.aggregator.num_clusters) / n
    return {"start R@1": out, "dustbin": dustbin, "dustbin mass": mass}


def _check_seeds(seeds) -> tuple[int, ...]:
    if isinstance(seeds, (str, bytes)) or not hasattr(seeds, "__iter__"):
        raise ValueError(f"seeds must be a list of training seeds, got {seeds!r}")
    seeds = tuple(check_int(s, "seed", minimum=0) for s in seeds)
    if not seeds or len(set(seeds)) != len(seeds):
        raise ValueError(f"seeds must list distinct training seeds, at least one, got {seeds}")
    return seeds


def _rounded(values: dict, digits: int = 4) -> dict:
    return {k: round(float(v), digits) for k, v in values.items()}


def _dustbin_record(arm: dict, starts: dict, seed: int) -> dict:
    """The trained Sinkhorn arm's dustbin for the first seed (from run_arms' per-seed lists) and its start's."""
    labels = [n for n in LABEL_NAMES if SHARE.format(n) in arm]
    start = starts["dustbin"]
    return {"seed": seed, "images": EXPERIMENT["dustbin"]["images"],
            "by construction (n - m) / n": round(starts["dustbin mass"], 4),
            "trained": {"share by label": {n: arm[SHARE.format(n)][0] for n in labels}, MEAN: arm[MEAN][0],
                        AUC: arm[AUC][0]},
            "start": {"share by label": _rounded({n: start[SHARE.format(n)] for n in labels}),
                      **_rounded({MEAN: start[MEAN], AUC: start[AUC]})}}


def run(seeds=SEEDS, workers: int = 2, max_epochs: int | None = None, select=None) -> dict:
    """The reproduce profile: both arms in both worlds, the premise record and the dustbin's measurement
    (``max_epochs``: a shorter run, e.g. a smoke test; None: the recipe's). Returns ``{"arms": {world: {arm:
    run_arms' entry}}, "premise": record, "dustbin": {world: {...}}}``; each arm's ``"start R@1"`` is its own
    (:func:`start_values`), and the Sinkhorn arm also holds the per-seed dustbin shares and :data:`AUC`.
    ``select`` (:class:`vpr_nb.recipe.arms.Selection`): only those arms and seeds, returned as ``{"arms"}``."""
    seeds = _check_seeds(seeds)
    workers = check_int(workers, "workers")
    recipe = RECIPE_ARMS
    if max_epochs is not None:
        recipe = dataclasses.replace(recipe, max_epochs=check_int(max_epochs, "max_epochs"))
    arms, dustbin, values = {}, {}, {}
    for world in RATES:
        train, val, tests = world_splits(world)
        sample = labelled_sample(tests)
        found = run_arms({world: {"train": train, "methods": methods()}}, val, tests, seeds, recipe,
                         workers=workers, lr=recipe.lr, select=select,
                         extra=lambda model, _tests, s=sample: dustbin_values(model, *s))
        if select is not None:
            arms.update(found)
            continue
        found = found[world]
        starts = start_values(train, tests, seeds, recipe, sample)
        for name, recalls in starts["start R@1"].items():
            found[name]["start R@1"] = recalls
        arms[world] = found
        dustbin[world] = _dustbin_record(found[COMPARISON[0]], starts, seeds[0])
        values[world] = {**premise_values(tests), "test queries": found[COMPARISON[0]]["test queries"],
                         f"{AUC}, trained Sinkhorn (seed {seeds[0]})": dustbin[world]["trained"][AUC]}
    if select is not None:
        return {"arms": arms}
    a, b = COMPARISON
    record = premise_record(QUANTITY, REAL_DATA, values,
                            {f"{a} − {b}": {w: paired_differences(arms[w][a]["R@1"], arms[w][b]["R@1"])
                                            for w in RATES}})
    return {"arms": arms, "premise": record, "dustbin": dustbin}
