"""DW-T-Loss's premise experiment (notebook 03): the distance weight of Eq. (4) where it can rank, and where not.

Eq. (4), ``w = (1 + eps) / (geo_qp / sigma + eps) - 1``, ranks a query's triplets by how far its positive is.
That ranking can matter only if the positives training uses lie at *different* distances on the scale of sigma
(the premise, measured by the coefficient of variation of w over the trained-on positives):

- **premise on**: one positive drawn at random among the potential positives within 15 m (the step's seeded
  stream, :class:`vpr_nb.recipe.TripletBatches`), sigma = 18 m: w runs from 10 down to about 0.2;
- **premise off**: NetVLAD's best positive within 10 m (the course's rule) and the paper's sigma = 800 m:
  w is 8.8-10, a loss scale.

In each world four arms train with the course recipe, each with its own lr search (chosen on the mean over
seeds 0-2, ``Recipe.search_seeds``), and one deviation the same for every arm (:data:`RECIPE_ARMS`, also the
positive control's, :mod:`vpr_nb.onoff.dwt_control`): the start is not a selection candidate, so with the
recipe's patience of 6 epochs early stopping cannot hide an arm that improves late: T-Loss (Eq. 3), CE-Loss (Eqs. 5-8),
DW-T-Loss (Eq. 9) and its placebo (Eq. 9 with the batch's distances permuted,
:class:`vpr_nb.losses.PlaceboDWTripletLoss`: the same weights, no link to the triplet). Beside it, the paper's own
protocol: the four losses under SGD (momentum 0.9) at one lr, the paper's 1e-4 and the course's 1e-3, in the
off world (the paper's setting), where DW-T's weight multiplies the step by about 9.
"""
from __future__ import annotations

import dataclasses

from ..losses import CETripletLoss, DWTripletLoss, PlaceboDWTripletLoss, TripletLoss
from ..losses import DEFAULT_EPS, DEFAULT_MARGIN
from ..premise import dwt as premise_dwt
from ..premise.record import paired_differences, premise_record
from ..recipe import RECIPE, VALIDATION_WORLD, Method, build_start, validation_split
from ..recipe.arms import CITY_TEST_WORLDS, run_arms, test_splits
from ..recipe.start import TripletBatches
from ..synthetic import make_dataset

WORLDS = {"on": {"positive": "random", "radius": 15.0, "sigma": 18.0},
          "off": {"positive": "best", "radius": 10.0, "sigma": 800.0}}
SEEDS = tuple(range(8))                # 8 paired seeds: the paper's headline comparison
SGD_LRS = (1e-4, 1e-3)                 # the paper's lr and the course's
RECIPE_ARMS = dataclasses.replace(RECIPE, initial_candidate=False)   # lr chosen on seeds 0-2
RECIPE_SGD = dataclasses.replace(RECIPE, optimizer="sgd")   # the paper's protocol: SGD, else the course recipe
COMPARISONS = (("DW-T-Loss", "T-Loss"), ("DW-T-Loss", "placebo"), ("DW-T-Loss", "CE-Loss"), ("CE-Loss", "T-Loss"))
REAL_DATA = {"value": "w 8.78-10.0 (CV 0.031)",
             "source": "Eq. (4) at sigma = 800 m for positives spread uniformly over NetVLAD's 10 m training radius "
                       "(Pittsburgh30k as the paper trains; the mined distances are not published, so uniform is an "
                       "assumption)"}
EXPERIMENT = {
    "train world": {"preset": "city", "seed": 0, "size": "tiny"},
    "worlds": {"validation": VALIDATION_WORLD, **{f"test, city seed {w['seed']}": w for w in CITY_TEST_WORLDS}},
    "premise worlds": WORLDS,
    "recipe": RECIPE_ARMS.to_dict(),
    "arms": ["T-Loss", "CE-Loss", "DW-T-Loss", "placebo"],
    "aggregator": "netvlad",
    "eps": DEFAULT_EPS, "margin": DEFAULT_MARGIN,
    "sgd": {"world": "off", "optimizer": "sgd", "momentum": 0.9, "lrs": list(SGD_LRS), "recipe": RECIPE_SGD.to_dict()},
    "seeds": list(SEEDS),
    "premise quantity": "coefficient of variation of Eq. (4)'s weight over the positives training uses",
}


def methods(world: str) -> list[Method]:
    """The four arms of ``world`` (``"on"`` or ``"off"``), NetVLAD-16, with that world's positives and sigma."""
    if world not in WORLDS:
        raise ValueError(f"world must be one of {sorted(WORLDS)}, got {world!r}")
    return world_methods(WORLDS[world])


def world_methods(w) -> list[Method]:
    """The four arms, NetVLAD-16, for a world ``{"positive": rule, "radius": metres, "sigma": metres}`` (also
    :mod:`vpr_nb.onoff.dwt_control`'s worlds)."""
    batches = TripletBatches(f"triplets, {w['positive']} positive within {w['radius']:g} m", w["positive"],
                             w["radius"])
    losses = {"T-Loss": TripletLoss(margin=DEFAULT_MARGIN), "CE-Loss": CETripletLoss(),
              "DW-T-Loss": DWTripletLoss(sigma=w["sigma"], eps=DEFAULT_EPS),
              "placebo": PlaceboDWTripletLoss(sigma=w["sigma"], eps=DEFAULT_EPS)}
    return [Method(name, "netvlad", loss, batches=batches) for name, loss in losses.items()]


def premise_values(train_split, seed: int = 0) -> dict:
    """The premise quantity in each world, on the training split: Eq. (4)'s weights over the positives that
    world's rule picks (the best rule with the recipe's NetVLAD start of ``seed``), and Spearman's rho of a
    positive's distance with its descriptor distance (is a far positive a worse one?)."""
    start = build_start(methods("off")[0], train_split, RECIPE_ARMS, seed)
    q, db = premise_dwt.split_descriptors(train_split, start)
    out = {}
    for world, w in WORLDS.items():
        dist = premise_dwt.mined_positive_distances(train_split, (q, db), w["radius"], w["positive"], seed)
        spread = premise_dwt.weight_spread(dist, w["sigma"], DEFAULT_EPS)
        rho = premise_dwt.usefulness_correlation(train_split, (q, db), w["radius"])
        out[world] = {"value": round(spread["cv"], 4), "weight min": round(spread["min"], 3),
                      "weight max": round(spread["max"], 3), "positives": spread["n"],
                      "distance median (m)": round(float(sorted(dist)[len(dist) // 2]), 2),
                      "spearman geo vs descriptor distance": round(rho["rho"], 3)}
    return out


def run(seeds=SEEDS, workers: int = 2, max_epochs: int | None = None, select=None) -> dict:
    """The reproduce profile: every arm in both worlds, the SGD table, and the premise record
    (``max_epochs``: a shorter run, e.g. a smoke test; None: the recipe's). ``select``
    (:class:`vpr_nb.recipe.arms.Selection`): only those arms and seeds, returned as ``{"arms", "sgd"}`` (to
    re-make one committed number)."""
    arms_recipe, sgd_recipe = capped(max_epochs, RECIPE_ARMS, RECIPE_SGD)
    train, val, tests = splits()
    arms = run_arms({w: {"train": train, "methods": methods(w)} for w in WORLDS}, val, tests, seeds, arms_recipe,
                    workers=workers, select=select)
    sgd = {}
    for lr in SGD_LRS:
        fixed = select if select is None else dataclasses.replace(select, lrs=None)
        sgd[f"{lr:g}"] = run_arms({"off": {"train": train, "methods": methods("off")}}, val, tests, seeds,
                                  sgd_recipe, workers=workers, lr=lr, select=fixed).get("off", {})
    if select is not None:
        return {"arms": arms, "sgd": sgd}
    record = arms_record(arms, premise_values(train), EXPERIMENT["premise quantity"], REAL_DATA)
    return {"arms": arms, "sgd": sgd, "premise": record}


def capped(max_epochs: int | None, *recipes):
    """``recipes`` with ``max_epochs`` (None: as they are)."""
    return tuple(r if max_epochs is None else dataclasses.replace(r, max_epochs=max_epochs) for r in recipes)


def splits() -> tuple:
    """03's training split (city seed 0), validation split and test splits."""
    return (make_dataset("city", seed=0, splits=("train",)).train, validation_split(VALIDATION_WORLD),
            test_splits(CITY_TEST_WORLDS))


def arms_record(arms, values, quantity: str, real_data) -> dict:
    """The premise record of the four arms in the worlds ``on`` and ``off``: :data:`COMPARISONS` per world, each
    world's premise ``values`` with the test queries."""
    queries = arms["off"]["T-Loss"]["test queries"]
    return premise_record(quantity, real_data, {w: {**values[w], "test queries": queries} for w in ("on", "off")},
                          {f"{a} − {b}": {w: paired_differences(arms[w][a]["R@1"], arms[w][b]["R@1"])
                                          for w in ("on", "off")} for a, b in COMPARISONS})
