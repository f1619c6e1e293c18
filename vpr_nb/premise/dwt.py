"""DW-T-Loss's premise, measured: the distances of the positives training mines, and what Eq. (4) makes of them.

DW-T-Loss (Xiong, Xu, Meng) weights each triplet by Eq. (4), ``w = (1 + eps) / (geo_qp / sigma + eps) - 1``
(:func:`vpr_nb.losses.distance_weight`), a decreasing function of the query-positive distance ``geo_qp`` in
metres. The weight can only rank triplets if the positives that training actually uses lie at different
distances *on the scale of sigma*: NetVLAD's best-positive rule (the potential positive within the training
radius that is nearest in descriptor space) mostly picks the nearest view, and at sigma = 800 m every
distance of a 10 m radius gets nearly the same weight (about 9.96 to 8.80 for eps = 0.1), so Eq. (4) scales
the loss and ranks nothing. This module measures that, for a notebook table:

==================================  ===================================================================
:func:`mined_positive_distances`    the query-positive distances of the positives a rule picks
                                    (``"best"``: NetVLAD's; ``"random"``: one drawn within the radius)
:func:`weight_spread`               Eq. (4)'s weights over those distances: min, max, max/min, mean, CV
:func:`premise_table`               one row per rule, radius and sigma (n, distance median and p90, CV,
                                    max/min)
:func:`usefulness_correlation`      Spearman's rho between a positive's geographic distance and its
                                    descriptor distance (is a far positive a worse one, as Eq. (4) assumes?)
==================================  ===================================================================

The rules are :func:`vpr_nb.mining.mine_triplets`' own (``positive="best"`` / ``"random"``), so the table
describes the positives :class:`vpr_nb.training.TripletSource` trains on.
"""
from __future__ import annotations

import numpy as np
import torch
from scipy.stats import spearmanr

from .._checks import check_positive
from ..evaluation import compute_descriptors
from ..losses import DEFAULT_EPS, distance_weight
from ..mining import check_positive_rule, mine_triplets
from ..split import check_split

DEFAULT_RADII = (10.0, 15.0, 25.0)      # NetVLAD's training radius, the pilot's, the evaluation radius (metres)
DEFAULT_SIGMAS = (800.0,)               # the paper's sigma (metres)
DEFAULT_SIGMA_FACTORS = (1.2,)          # sigma = factor x radius: the pilot's 18 m at a 15 m radius
DEFAULT_HEADING_DIFF = 45.0             # the course's max_heading_diff (notebook 03's HEADING_DIFF)


def _check_split(split):
    split = check_split(split, "split")
    if not split.has_queries or len(split.db_utm) == 0:
        raise ValueError(f"the split {split.name} is empty: it needs queries and database images (mined positives "
                         "pair a query with a database image)")
    return split


def _check_radius(radius) -> float:
    r = check_positive(radius, "radius")
    if not np.isfinite(r):
        raise ValueError(f"radius must be a finite number of metres, got {radius!r}")
    return r


def split_descriptors(split, model_or_descriptors) -> tuple[np.ndarray, np.ndarray]:
    """``(q_desc, db_desc)`` of ``split``: computed by a model (:func:`vpr_nb.evaluation.compute_descriptors`),
    or given as a pair of ``(Q, D)`` and ``(N, D)`` arrays, checked against the split's sizes."""
    split = _check_split(split)
    if isinstance(model_or_descriptors, torch.nn.Module):
        return (compute_descriptors(model_or_descriptors, split.q_images),
                compute_descriptors(model_or_descriptors, split.db_images))
    if not isinstance(model_or_descriptors, (tuple, list)) or len(model_or_descriptors) != 2:
        raise ValueError("model_or_descriptors must be a torch model or a pair (q_desc, db_desc) of descriptor "
                         f"arrays, got {type(model_or_descriptors).__name__}")
    q, db = (np.asarray(d, dtype=np.float32) for d in model_or_descriptors)
    nq, ndb = len(split.q_utm), len(split.db_utm)
    if q.ndim != 2 or db.ndim != 2 or q.shape[0] != nq or db.shape[0] != ndb or q.shape[1] != db.shape[1]:
        raise ValueError(f"descriptors must be (Q, D) = ({nq}, D) and (N, D) = ({ndb}, D) for the split "
                         f"{split.name}, got {q.shape} and {db.shape}")
    if not (np.isfinite(q).all() and np.isfinite(db).all()):
        raise ValueError("descriptors contain NaN or inf")
    return q, db


def _heading(split, max_heading_diff) -> dict:
    if max_heading_diff is None:
        return {}
    if split.q_heading is None or split.db_heading is None:
        raise ValueError(f"max_heading_diff={max_heading_diff} needs camera headings, and the split {split.name} has "
                         "none: pass max_heading_diff=None")
    return dict(q_heading=split.q_heading, db_heading=split.db_heading, max_heading_diff=max_heading_diff)


def _mined(split, descriptors, radius: float, rule: str, seed: int, max_heading_diff):
    """The mined positives of every query with one: ``(query ids, positive ids, geo_qp)``."""
    nq, ndb = len(split.q_utm), len(split.db_utm)
    if descriptors is None:                # the random rule reads no descriptor: any will do
        descriptors = (np.zeros((nq, 1), np.float32), np.zeros((ndb, 1), np.float32))
    q, db = descriptors
    ids = np.arange(nq)
    neg = max(radius, split.pos_radius)
    tb = mine_triplets(q, db, split.q_utm, split.db_utm, ids, train_pos_radius=radius, neg_radius=neg,
                       num_negatives=1, num_candidates=1, rng=0, positives=split.positives(radius),
                       near=split.positives(neg), positive=rule, positive_seed=seed, **_heading(split, max_heading_diff))
    has = tb.positive >= 0
    return ids[has], tb.positive[has], tb.geo_qp[has]


def mined_positive_distances(split, model_or_descriptors=None, radius: float = 10.0, rule: str = "best",
                             seed: int = 0, max_heading_diff: float | None = DEFAULT_HEADING_DIFF) -> np.ndarray:
    """The geographic query-positive distances (metres) of the positives ``rule`` picks: the ``geo_qp`` that
    Eq. (4) of DW-T-Loss turns into weights, one per trainable query (a query with a potential positive within
    ``radius`` that faces within ``max_heading_diff`` degrees of it; None: any heading).

    ``rule``: ``"best"`` (NetVLAD's rule: the potential positive nearest in descriptor space, which needs
    ``model_or_descriptors``, a torch model or a pair ``(q_desc, db_desc)``) or ``"random"`` (one drawn
    uniformly, query ``i`` from :func:`vpr_nb.mining.positive_rng` ``(seed, i)``; descriptors are not read).
    The potential positives are ``split.positives(radius)`` (inside each region), as in training.
    """
    split = _check_split(split)
    radius = _check_radius(radius)
    rule = check_positive_rule(rule)
    if rule == "best" and model_or_descriptors is None:
        raise ValueError("rule='best' picks the positive nearest in descriptor space: pass model_or_descriptors "
                         "(a model or a pair (q_desc, db_desc))")
    desc = None if model_or_descriptors is None else split_descriptors(split, model_or_descriptors)
    return _mined(split, desc, radius, rule, seed, max_heading_diff)[2]


def weight_spread(distances, sigma: float, eps: float = DEFAULT_EPS) -> dict[str, float]:
    """How much Eq. (4)'s weights ``w = (1 + eps) / (d / sigma + eps) - 1`` vary over ``distances`` (metres),
    computed with :func:`vpr_nb.losses.distance_weight`.

    Returns ``n``, ``min``, ``max``, ``max_over_min`` (inf when some weight is <= 0, i.e. a distance >= sigma),
    ``mean`` and ``cv``, the coefficient of variation std / mean (population std; NaN when the mean is <= 0).
    A CV near 0 means the weight is a constant factor: it rescales the loss (and the learning rate) and ranks
    no triplet above another.
    """
    d = np.asarray(distances, dtype=np.float64)
    if d.ndim != 1 or len(d) == 0:
        raise ValueError(f"distances must be a non-empty 1-D array of metres, got shape {d.shape}: no positive "
                         "was mined (check the radius and the split)")
    w = distance_weight(d, sigma, eps)
    lo, hi, mean = float(w.min()), float(w.max()), float(w.mean())
    return {"n": int(len(w)), "min": lo, "max": hi, "max_over_min": hi / lo if lo > 0 else float("inf"),
            "mean": mean, "cv": float(w.std()) / mean if mean > 0 else float("nan")}


def premise_table(split, descriptors=None, radii=DEFAULT_RADII, rules=("best", "random"), sigmas=DEFAULT_SIGMAS,
                  sigma_factors=DEFAULT_SIGMA_FACTORS, eps: float = DEFAULT_EPS, seed: int = 0,
                  max_heading_diff: float | None = DEFAULT_HEADING_DIFF) -> list[dict]:
    """Rows for notebook 03's premise table: for each rule, radius and sigma, how spread Eq. (4)'s weights are
    over the positives that rule mines (:func:`mined_positive_distances`, :func:`weight_spread`).

    ``descriptors``: a model or a pair ``(q_desc, db_desc)`` (computed once; needed by the best rule).
    ``sigmas`` are in metres; ``sigma_factors`` add, per radius, ``sigma = factor x radius`` (sigma on the
    scale of the positives; a sigma that both give appears once). Each row: ``rule``, ``radius``, ``sigma``, ``n`` (trainable queries),
    ``dist_median`` and ``dist_p90`` (metres), ``weight_min``, ``weight_max``, ``weight_cv`` and
    ``weight_max_over_min``.
    """
    split = _check_split(split)
    radii = [_check_radius(r) for r in radii]
    rules = [check_positive_rule(r) for r in rules]
    if not radii or not rules:
        raise ValueError("radii and rules must each name at least one value")
    sigmas = [check_positive(s, "sigma") for s in sigmas]
    factors = [check_positive(f, "sigma factor") for f in sigma_factors]
    if not sigmas and not factors:
        raise ValueError("give at least one sigma (sigmas in metres or sigma_factors x radius)")
    if "best" in rules and descriptors is None:
        raise ValueError("the best rule picks positives by descriptor distance: pass descriptors (a model or a "
                         "pair (q_desc, db_desc))")
    desc = None if descriptors is None else split_descriptors(split, descriptors)
    rows = []
    for rule in rules:
        for radius in radii:
            d = _mined(split, desc, radius, rule, seed, max_heading_diff)[2]
            if len(d) == 0:
                raise ValueError(f"no query of {split.name} has a potential positive within {radius:g} m "
                                 f"(rule {rule!r}); use a larger radius")
            for sigma in dict.fromkeys(sigmas + [f * radius for f in factors]):   # each sigma once per radius
                s = weight_spread(d, sigma, eps)
                rows.append({"rule": rule, "radius": radius, "sigma": sigma, "n": s["n"],
                             "dist_median": float(np.median(d)), "dist_p90": float(np.percentile(d, 90)),
                             "weight_min": s["min"], "weight_max": s["max"], "weight_cv": s["cv"],
                             "weight_max_over_min": s["max_over_min"]})
    return rows


def usefulness_correlation(split, model_or_descriptors, radius: float = 10.0, rule: str | None = None,
                           seed: int = 0, max_heading_diff: float | None = DEFAULT_HEADING_DIFF) -> dict:
    """Spearman's rank correlation between positives' geographic distance (metres) and descriptor distance
    (Euclidean, as mining measures it): Eq. (4) gives a far positive less weight, which helps only if a far
    positive is a worse one, i.e. if rho > 0.

    ``rule=None`` correlates every potential positive pair (within ``radius``, facing within
    ``max_heading_diff``); ``"best"`` / ``"random"`` only the positive each query gets under that rule.
    Returns ``rho`` and ``pvalue`` (pooled over the pairs, :func:`scipy.stats.spearmanr`), ``n`` (pairs) and,
    for ``rule=None``, ``rho_within``: the mean of the per-query rhos (queries with at least 3 potential
    positives whose distances vary), which the differences between queries do not drive (NaN when none).
    """
    split = _check_split(split)
    radius = _check_radius(radius)
    q, db = split_descriptors(split, model_or_descriptors)
    if rule is not None:
        qi, pi, geo = _mined(split, (q, db), radius, check_positive_rule(rule), seed, max_heading_diff)
        desc = np.linalg.norm(q[qi] - db[pi], axis=1)
        within = []
    else:
        h = _heading(split, max_heading_diff)
        geo_parts, desc_parts, within = [], [], []
        for i, pos in enumerate(split.positives(radius)):
            if h:
                diff = np.abs((np.asarray(split.db_heading, float)[pos] - float(split.q_heading[i]) + 180.0)
                              % 360.0 - 180.0)
                pos = pos[diff <= max_heading_diff]
            if len(pos) == 0:
                continue
            g = np.linalg.norm(split.db_utm[pos] - split.q_utm[i], axis=1)
            e = np.linalg.norm(db[pos] - q[i], axis=1)
            geo_parts.append(g)
            desc_parts.append(e)
            if len(pos) >= 3 and np.ptp(g) > 0 and np.ptp(e) > 0:
                within.append(float(spearmanr(g, e).statistic))
        geo = np.concatenate(geo_parts) if geo_parts else np.zeros(0)
        desc = np.concatenate(desc_parts) if desc_parts else np.zeros(0)
    if len(geo) < 3:
        raise ValueError(f"only {len(geo)} positive pairs within {radius:g} m: a rank correlation needs at least 3")
    res = spearmanr(geo, desc)
    out = {"rho": float(res.statistic), "pvalue": float(res.pvalue), "n": int(len(geo))}
    if rule is None:
        out["rho_within"] = float(np.mean(within)) if within else float("nan")
    return out


__all__ = ["mined_positive_distances", "weight_spread", "premise_table", "usefulness_correlation",
           "split_descriptors", "DEFAULT_RADII", "DEFAULT_SIGMAS", "DEFAULT_SIGMA_FACTORS", "DEFAULT_HEADING_DIFF"]
