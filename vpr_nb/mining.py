"""Which pairs or triplets a loss sees: descriptor miners (NetVLAD hard negatives).

* :func:`mine_triplets` -- NetVLAD (Arandjelovic et al., CVPR 2016) weakly supervised triplets:
  best positive within 10 m, hardest negatives beyond 25 m, with a per-query negative cache; or
  (``positive="random"``) one potential positive drawn at random, which DW-T-Loss's Eq. (4) can rank.

The geotag/place batch samplers (CliqueMining, random places, batch statistics) are in
:mod:`vpr_nb.samplers`, as pytorch-metric-learning keeps samplers apart from miners.

Every function takes a ``np.random.Generator`` (or an int seed) and returns the same output for
the same seed. Distances between geotags are Euclidean distances of UTM (easting, northing) in metres.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ._checks import check_geo_descriptors, check_int, check_positive
from .samplers._common import _as_rng, _dist
from .split import positives_within
from ._threads import single_threaded_call

POSITIVE_RULES = ("best", "random")
"""How :func:`mine_triplets` picks a query's positive among its potential positives: ``"best"`` (NetVLAD's
Eq. (7): the nearest in descriptor space) or ``"random"`` (one drawn uniformly at random)."""


def check_positive_rule(positive) -> str:
    """``positive`` itself when it is one of :data:`POSITIVE_RULES`, else ValueError naming them."""
    if not isinstance(positive, str) or positive not in POSITIVE_RULES:
        raise ValueError(f"positive must be one of {POSITIVE_RULES} (the nearest potential positive in descriptor "
                         f"space, or one drawn at random), got {positive!r}")
    return positive


def _seed_sequence(seed) -> np.random.SeedSequence:
    if isinstance(seed, np.random.SeedSequence):
        return seed
    try:
        return np.random.SeedSequence(seed)
    except (TypeError, ValueError):
        raise ValueError(f"positive_seed must be a non-negative int, a sequence of them (e.g. (seed, epoch)) or a "
                         f"np.random.SeedSequence, got {seed!r}") from None


def positive_rng(seed, query: int) -> np.random.Generator:
    """The generator that draws query ``query``'s random positive: child ``query`` of ``seed`` (an int, a
    sequence of ints such as ``(seed, epoch)``, or a ``np.random.SeedSequence``), independent of the model
    and of the order in which queries are mined."""
    ss = _seed_sequence(seed)
    return np.random.default_rng(np.random.SeedSequence(ss.entropy, spawn_key=(*ss.spawn_key, int(query)),
                                                        pool_size=ss.pool_size))


# ----------------------------------------------------------------------------- NetVLAD triplets
@dataclass(frozen=True, eq=False)
class TripletBatch:
    """Mined NetVLAD tuples ``(query, positive, negatives)``, one row per requested query.

    Attributes:
        query: ``(B,)`` query indices (into the query arrays).
        positive: ``(B,)`` database index of the positive (the best one, or the random one with
            ``positive="random"``), -1 for queries without a potential positive.
        negatives: ``(B, M)`` database indices of the M hardest negatives, hardest first
            (-1 for queries without a positive or with fewer than M negatives).
        negative_mask: ``(B, M)`` True where the negative violates the margin
            (all True when ``margin`` is None; all False for invalid queries).
        geo_qp: ``(B,)`` query-positive distance in metres (NaN for invalid queries).
        valid: ``(B,)`` True for queries to train on.
        neg_cache: ``{query index: (M,) negatives}``, updated for every query with a positive.
    """

    query: np.ndarray
    positive: np.ndarray
    negatives: np.ndarray
    negative_mask: np.ndarray
    geo_qp: np.ndarray
    valid: np.ndarray
    neg_cache: dict[int, np.ndarray]


def _rows(lists, n: int, what: str, n_db: int) -> list[np.ndarray]:
    if len(lists) != n:
        raise ValueError(f"{what} must hold one index array per query of query_ids ({n}), got {len(lists)}")
    rows = [np.asarray(r, dtype=np.int64).reshape(-1) for r in lists]
    if any(len(r) and (r.min() < 0 or r.max() >= n_db) for r in rows):
        raise ValueError(f"{what} must hold database indices in [0, {n_db - 1}]")
    return rows


def _sq_dist(q: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Squared Euclidean distances from vector ``q`` to each row of ``x`` (one matmul)."""
    return np.maximum(np.einsum("ij,ij->i", x, x) - 2.0 * (x @ q) + q @ q, 0.0)


@single_threaded_call   # many small products: one BLAS thread (vpr_nb._threads)
def mine_triplets(q_desc, db_desc, q_utm, db_utm, query_ids, *, train_pos_radius: float = 10.0,
                  neg_radius: float = 25.0, num_negatives: int = 10, num_candidates: int = 1000,
                  neg_cache: dict[int, np.ndarray] | None = None, rng, margin: float | None = None,
                  q_heading=None, db_heading=None, max_heading_diff: float | None = None,
                  positives=None, near=None, positive: str = "best", positive_seed=None) -> TripletBatch:
    """NetVLAD weakly supervised tuple mining (Arandjelovic et al., CVPR 2016, Sec. 4, Eq. (7)).

    For each query in ``query_ids``:

    * positive: among the database images within ``train_pos_radius`` m (inclusive), the one
      nearest in descriptor space (Eq. (7) takes the best of the potential positives); with
      ``positive="random"``, one of them drawn uniformly at random (the best rule mostly picks the
      nearest view; random positives spread over the radius, which DW-T-Loss's Eq. (4) can rank);
    * candidate negatives: ``num_candidates`` images drawn uniformly *without replacement* among
      the database images farther than ``neg_radius`` m, plus the query's cached negatives
      (those farther than ``neg_radius`` m);
    * negatives: the ``num_negatives`` (M) candidates nearest to the query in descriptor space,
      sorted hardest (nearest) first.

    Optionally (``max_heading_diff`` with ``q_heading``/``db_heading`` in degrees) a potential
    positive must also face the same way as the query, ``|Δheading| ≤ max_heading_diff``: with
    several headings per place (Pittsburgh's 24 views), an image 5 m away that looks the other way
    shares no content, and a randomly initialised network cannot tell which potential positive is
    the right view (an ImageNet-pretrained one mostly can). Negatives ignore headings.

    Distances are plain Euclidean distances. With ``margin=None`` the M hardest are kept (as in
    the deep-visual-geo-localization-benchmark). With a ``margin`` (same units), ``negative_mask``
    marks the negatives that violate it, ``d(q, n) < d(q, p) + margin``, and a query with no
    violating negative is invalid (as in pytorch-NetVlad, which skips it); the loss should use only
    masked negatives. A query is also invalid when it has no positive or fewer than M negatives.
    The cache entry of every query with a positive and M negatives is replaced by its M hardest
    negatives; pass the returned ``neg_cache`` back in at the next call.

    Args:
        q_desc: ``(Q, D)`` query descriptors (e.g. L2-normalised, float32).
        db_desc: ``(N, D)`` database descriptors.
        q_utm: ``(Q, 2)`` query positions, metres.
        db_utm: ``(N, 2)`` database positions, metres.
        query_ids: ``(B,)`` indices of the queries to mine for.
        train_pos_radius: positives are within this many metres (10 in NetVLAD).
        neg_radius: negatives are farther than this (25); must be >= train_pos_radius.
        num_negatives: M negatives per query (10).
        num_candidates: random negatives sampled per query (1000); must be >= M.
        neg_cache: dict from query index to its cached negatives, updated in place (or None).
        rng: ``np.random.Generator`` (or an int seed).
        margin: optional triplet margin for the violation mask.
        q_heading, db_heading: ``(Q,)`` and ``(N,)`` camera headings in degrees (only with
            ``max_heading_diff``).
        max_heading_diff: keep only potential positives within this many degrees of the query's
            heading (None: any heading, the NetVLAD rule).
        positives, near: for each of ``query_ids``, the database images within ``train_pos_radius``
            (the potential positives) and within ``neg_radius`` (never negatives), e.g. rows of a split's
            ``positives(train_pos_radius)`` / ``positives(neg_radius)``, which stay inside each region
            (city). None: the radius search of ``q_utm`` / ``db_utm`` (:func:`vpr_nb.split.positives_within`).
        positive: ``"best"`` (default, NetVLAD's rule) or ``"random"`` (:data:`POSITIVE_RULES`).
        positive_seed: with ``positive="random"``, the seed of the draws (an int, a sequence of ints such as
            ``(seed, epoch)``, or a ``np.random.SeedSequence``): query ``i`` draws from
            :func:`positive_rng` ``(positive_seed, i)``, so the draw depends neither on the model nor on ``rng``,
            whose stream (the negatives) stays the best rule's. None: drawn from ``rng``, after the query's
            negative candidates. Ignored by the best rule, which draws nothing.
    """
    qd, dbd, qu, du = check_geo_descriptors(q_desc, db_desc, q_utm, db_utm)
    ids = np.asarray(query_ids)
    if ids.ndim != 1 or len(ids) == 0 or not np.issubdtype(ids.dtype, np.integer):
        raise ValueError(f"query_ids must be a non-empty 1-D integer array, got {ids.dtype} of shape {ids.shape}")
    if ids.min() < 0 or ids.max() >= len(qd):
        raise ValueError(f"query_ids must lie in [0, {len(qd) - 1}], got range [{ids.min()}, {ids.max()}]")
    pos_r = check_positive(train_pos_radius, "train_pos_radius")
    neg_r = check_positive(neg_radius, "neg_radius")
    if neg_r < pos_r:
        raise ValueError(f"neg_radius ({neg_r}) must be >= train_pos_radius ({pos_r}), otherwise an image "
                         "could be both a positive and a negative")
    m = check_int(num_negatives, "num_negatives")
    c = check_int(num_candidates, "num_candidates")
    if c < m:
        raise ValueError(f"num_candidates ({c}) must be >= num_negatives ({m})")
    if margin is not None:
        margin = check_positive(margin, "margin", allow_zero=True)
    if neg_cache is None:
        neg_cache = {}
    elif not isinstance(neg_cache, dict):
        raise ValueError(f"neg_cache must be a dict {{query index: negatives}} or None, got {type(neg_cache).__name__}")
    rng = _as_rng(rng)
    rule = check_positive_rule(positive)
    if rule == "random" and positive_seed is not None:
        positive_seed = _seed_sequence(positive_seed)
    if max_heading_diff is not None:
        max_heading_diff = check_positive(max_heading_diff, "max_heading_diff")
        if q_heading is None or db_heading is None:
            raise ValueError("max_heading_diff needs q_heading and db_heading (degrees, one per image)")
        qh = np.asarray(q_heading, dtype=np.float64)
        dh = np.asarray(db_heading, dtype=np.float64)
        if qh.shape != (len(qd),) or dh.shape != (len(dbd),) or not (np.isfinite(qh).all() and np.isfinite(dh).all()):
            raise ValueError(f"q_heading must have shape ({len(qd)},) and db_heading ({len(dbd)},), finite "
                             f"degrees; got {qh.shape} and {dh.shape}")

    ids = ids.astype(np.int64)
    b = len(ids)
    positive = np.full(b, -1, dtype=np.int64)
    negatives = np.full((b, m), -1, dtype=np.int64)
    mask = np.zeros((b, m), dtype=bool)
    geo_qp = np.full(b, np.nan)
    valid = np.zeros(b, dtype=bool)
    n_db = len(dbd)
    pos_lists = positives_within(du, qu[ids], pos_r) if positives is None else _rows(positives, b, "positives", n_db)
    near_lists = positives_within(du, qu[ids], neg_r) if near is None else _rows(near, b, "near", n_db)
    is_near = np.zeros(n_db, dtype=bool)    # this query's images within neg_radius (never negatives)
    is_cand = np.zeros(n_db, dtype=bool)    # this query's candidate negatives
    for r, (qi, pos, close) in enumerate(zip(ids.tolist(), pos_lists, near_lists)):
        is_near[close] = True
        take = min(c, n_db - len(close))
        draw = rng.choice(n_db, size=min(n_db, take + len(close)), replace=False)
        sample = draw[~is_near[draw]][:take]  # uniform without replacement beyond neg_radius
        cached = np.asarray(neg_cache.get(qi, ()), dtype=np.int64)
        cached = cached[(cached >= 0) & (cached < n_db)]
        cached = cached[~is_near[cached]]      # still beyond neg_radius (as the sample)
        is_near[close] = False
        if max_heading_diff is not None:
            pos = pos[np.abs((dh[pos] - qh[qi] + 180.0) % 360.0 - 180.0) <= max_heading_diff]
        if len(pos) == 0:
            continue
        q = qd[qi]
        d_pos = np.sqrt(_sq_dist(q, dbd[pos]))
        if rule == "best":
            pick = int(np.argmin(d_pos))
        else:
            pick = int((rng if positive_seed is None else positive_rng(positive_seed, qi)).integers(len(pos)))
        positive[r], geo_qp[r] = pos[pick], _dist(qu[qi], du[pos[pick]])
        is_cand[sample] = is_cand[cached] = True
        cand = np.flatnonzero(is_cand)         # the union of both, ascending
        is_cand[cand] = False
        if len(cand) < m:
            continue
        d_neg = np.sqrt(_sq_dist(q, dbd[cand]))
        hardest = np.argsort(d_neg, kind="stable")[:m]
        negatives[r] = cand[hardest]
        neg_cache[qi] = cand[hardest]
        mask[r] = True if margin is None else d_neg[hardest] < d_pos[pick] + margin
        valid[r] = mask[r].any()
    return TripletBatch(query=ids, positive=positive, negatives=negatives, negative_mask=mask,
                        geo_qp=geo_qp, valid=valid, neg_cache=neg_cache)
