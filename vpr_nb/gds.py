"""Geographic Distance Sensitivity (GDS) of a VPR embedding.

CliqueMining (Izquierdo & Civera, ECCV 2024) argues that a VPR descriptor should keep sorting
images correctly *at small geographic distances*: among the top-k retrievals of a query, the
image taken 5 m away should be closer in descriptor space than the one taken 20 m away. The
paper plots, for image pairs binned by their geographic distance, the descriptor distance
(mean and spread, its Fig. 1). No public code for that analysis exists, so this module defines
it precisely:

Pair set
    ``pairs="query-db"``: every (query, database) pair whose geographic distance is
    ``<= max_distance``. ``pairs="all"``: every unordered pair ``i < j`` of one image set with
    geographic distance ``<= max_distance``. Pairs are found with a k-d tree range search on the
    2-D UTM positions, so memory is O(number of pairs), never O(N^2).
Distances
    geographic distance = Euclidean distance of the UTM (easting, northing) positions, in metres;
    descriptor distance = plain (unsquared) Euclidean distance ``||a - b||_2`` of the descriptors
    (for L2-normalised descriptors it lies in [0, 2] and equals ``sqrt(2 - 2 cos)``), computed in
    float32 as ``sqrt(max(|a|^2 + |b|^2 - 2 a.b, 0))`` from Gram matrices of the images that nearby pairs
    share, and from the difference ``a - b`` for near-duplicate descriptors (where the dot formula
    cancels); either way within float32 rounding of ``||a - b||_2``.
Bins
    ``B = ceil(max_distance / bin_width)`` bins of width ``bin_width`` starting at 0 m:
    bin ``b`` holds pairs with geographic distance in ``[b*w, (b+1)*w)``; the last bin is closed
    and also holds pairs at exactly ``max_distance``. ``bin_centers = (b + 0.5) * w``.
Per-bin statistics
    ``count``, ``mean`` and population standard deviation ``std`` (ddof = 0) of the descriptor
    distance, and the requested ``quantiles`` (numpy's ``"linear"`` method). Empty bins hold NaN.
Band
    the plot shades ``mean +- 1 std``.
Slope (units: descriptor-distance units per metre)
    weighted least-squares line ``mean_b ~ intercept + slope * center_b`` over the non-empty bins
    whose centre lies in ``fit_range`` (inclusive), with weights ``count_b``. This equals the
    ordinary least-squares fit over the raw pairs with each geographic distance replaced by its
    bin centre. A larger slope means the embedding separates near from far places better, i.e.
    a higher geographic distance sensitivity.
Mis-ordering probability
    ``P(D(d2) < D(d1))`` for ``d1 < d2``: the probability that a pair taken ``d2`` metres apart
    gets a *smaller* descriptor distance than a pair taken ``d1`` metres apart, so that the farther
    image is ranked first. ``"gaussian"`` models each bin as a normal distribution,
    ``Phi((mu1 - mu2) / sqrt(sigma1^2 + sigma2^2))``; ``"empirical"`` compares every sample of the
    two bins exactly (ties count one half).
"""
from __future__ import annotations

import math
import warnings
from dataclasses import dataclass
from typing import Sequence

import faiss
import numpy as np
from scipy.spatial import cKDTree
from scipy.special import ndtr

from vpr_nb._checks import as_float_matrix, as_utm, check_geo_descriptors, check_int, check_positive
from vpr_nb._threads import single_threaded, single_threaded_call

_PAIR_MODES = ("query-db", "all")
_METHODS = ("gaussian", "empirical")
_CHUNK_FLOATS = 1 << 17  # floats per temporary (512 KiB, cache-sized) in the chunked loops
_DESC_CHUNK_FLOATS = 1 << 18  # floats per gathered descriptor block (1 MiB)
_GRAM_CHUNK_PAIRS = 8192  # pairs per Gram-matrix lookup in _pair_descriptor_distances
_GRAM_MAX_WORK = 24  # Gram entries (symmetric: half) per pair above which a chunk uses the difference formula
                     # (a gathered-difference chunk costs about as much as a Gram matrix of ~35 entries per pair)
_SELECT_BUCKETS = 1 << 22  # most (bin, value) buckets of the quantile selection (_bin_order_statistics; 16 MiB of counts)
_CANCEL_FRACTION = np.float32(1 / 32)  # d^2 < (|a|^2 + |b|^2) * this: recompute from the difference


@dataclass(frozen=True, eq=False)
class GDSProfile:
    """Descriptor distance as a function of geographic distance (see the module docstring).

    Attributes:
        bin_edges: ``(B + 1,)`` bin edges in metres.
        bin_centers: ``(B,)`` bin centres in metres.
        count: ``(B,)`` number of pairs per bin.
        mean: ``(B,)`` mean descriptor distance per bin (NaN for empty bins).
        std: ``(B,)`` population standard deviation per bin (NaN for empty bins).
        quantiles: ``{q: (B,) array}`` descriptor-distance quantiles per bin.
        slope: fitted descriptor-distance units per metre over ``fit_range`` (NaN if < 2 bins).
        intercept: descriptor distance of the fitted line at 0 m.
        pairs: ``"query-db"`` or ``"all"``.
        fit_range: ``(lo, hi)`` metres used for the fit.
        pair_geo: ``(P,)`` geographic distance of every pair (only with ``keep_pairs=True``),
            sorted by bin, then by descriptor distance.
        pair_desc: ``(P,)`` descriptor distance of every pair, in the same order.
    """

    bin_edges: np.ndarray
    bin_centers: np.ndarray
    count: np.ndarray
    mean: np.ndarray
    std: np.ndarray
    quantiles: dict[float, np.ndarray]
    slope: float
    intercept: float
    pairs: str
    fit_range: tuple[float, float]
    pair_geo: np.ndarray | None = None
    pair_desc: np.ndarray | None = None

    @property
    def bin_width(self) -> float:
        """Width of every bin in metres."""
        return float(self.bin_edges[1] - self.bin_edges[0])

    def plot(self, ax=None, label: str | None = None, color=None):
        """Draw the mean descriptor distance, a +-1 std band and the dashed fit line (Fig. 1 style).

        Returns the matplotlib ``Axes``; x is geographic distance (m), y descriptor distance.
        """
        if ax is None:
            import matplotlib.pyplot as plt

            _, ax = plt.subplots(figsize=(5, 3.5))
        (line,) = ax.plot(self.bin_centers, self.mean, color=color, label=label, lw=1.8)
        color = line.get_color()
        ax.fill_between(self.bin_centers, self.mean - self.std, self.mean + self.std,
                        color=color, alpha=0.2, lw=0)
        if np.isfinite(self.slope):
            lo, hi = self.fit_range
            x = np.array([lo, min(hi, float(self.bin_edges[-1]))])
            ax.plot(x, self.intercept + self.slope * x, ls="--", color=color, lw=1.2)
        ax.set_xlabel("geographic distance (m)")
        ax.set_ylabel("descriptor distance (L2)")
        if label is not None:
            ax.legend()
        return ax


@dataclass(frozen=True, eq=False)
class OrderAgreement:
    """How well the top-k retrievals of each query are sorted by geographic distance.

    Attributes:
        topk: ``(Q, k)`` database indices retrieved per query, best first.
        topk_geo: ``(Q, k)`` geographic distance (m) from the query to each retrieval.
        fraction_correct: ``(Q,)`` fraction of retrieval pairs ``(a, b)``, ``a`` ranked before
            ``b``, with ``geo(a) <= geo(b)``.
        kendall_tau: ``(Q,)`` Kendall tau-b between rank and geographic distance (NaN when all
            k retrievals are at the same distance).
        mean_fraction_correct: mean of ``fraction_correct``.
        mean_kendall_tau: mean of ``kendall_tau`` over queries where it is defined.
    """

    topk: np.ndarray
    topk_geo: np.ndarray
    fraction_correct: np.ndarray
    kendall_tau: np.ndarray
    mean_fraction_correct: float
    mean_kendall_tau: float


def _geo_pairs(db_utm: np.ndarray, q_utm: np.ndarray | None, max_distance: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Index pairs ``(i, j)`` within ``max_distance`` and their geographic distances.

    With ``q_utm`` the pairs are (query i, database j); without it, unordered pairs i < j of db.
    The pairs come in the k-d tree's order (the per-bin sums below are taken in that order).
    """
    db_tree = cKDTree(db_utm)
    idx = np.int32 if max(len(db_utm), 0 if q_utm is None else len(q_utm)) < 2 ** 31 else np.int64
    if q_utm is None:
        ij = db_tree.query_pairs(max_distance, output_type="ndarray")
        i, j = ij[:, 0].astype(idx), ij[:, 1].astype(idx)   # 8 bytes per pair instead of 16
        del ij
        src = db_utm
    else:
        sparse = cKDTree(q_utm).sparse_distance_matrix(db_tree, max_distance, output_type="ndarray")
        i, j = sparse["i"].astype(idx), sparse["j"].astype(idx)
        del sparse
        src = q_utm
    # ``sqrt(((src[i] - db[j]) ** 2).sum(1))`` with the same float operations (the sum over the length-2
    # axis is x + y), from separate easting/northing columns and in bounded-memory chunks
    sx, sy = np.ascontiguousarray(src[:, 0]), np.ascontiguousarray(src[:, 1])
    dx_all, dy_all = np.ascontiguousarray(db_utm[:, 0]), np.ascontiguousarray(db_utm[:, 1])
    geo = np.empty(len(i), dtype=np.float64)
    step = _CHUNK_FLOATS
    for s in range(0, len(i), step):
        ii, jj = i[s:s + step], j[s:s + step]
        dx = sx[ii]
        dx -= dx_all[jj]
        dy = sy[ii]
        dy -= dy_all[jj]
        dx *= dx
        dy *= dy
        dx += dy
        np.sqrt(dx, out=geo[s:s + step])
    keep = geo <= max_distance  # the tree's own rounding may differ from ours by one ulp
    if keep.all():
        return i, j, geo
    return i[keep], j[keep], geo[keep]


def _distinct(idx: np.ndarray, pos: np.ndarray, arange: np.ndarray) -> np.ndarray:
    """The distinct values ``u`` of ``idx`` (in first-representative order, no sort) and ``pos[u] = 0..len(u)-1``.

    ``pos`` is a scratch array over the whole index range: after ``pos[idx] = position``, exactly one
    position per distinct value reads its own position back, whichever duplicate was written last.
    """
    ar = arange[:len(idx)]
    pos[idx] = ar
    u = idx[pos[idx] == ar]
    pos[u] = arange[:len(u)]
    return u


def _direct_distances_sq(a: np.ndarray, b: np.ndarray, i: np.ndarray, j: np.ndarray) -> np.ndarray:
    """``||a[i] - b[j]||^2`` per pair from the gathered difference (float32), in blocks of 1 MiB."""
    out = np.empty(len(i), dtype=np.float32)
    step = max(1, _DESC_CHUNK_FLOATS // a.shape[1])
    for s in range(0, len(i), step):
        diff = a[i[s:s + step]]
        diff -= b[j[s:s + step]]
        np.einsum("ij,ij->i", diff, diff, out=out[s:s + step])
    return out


def _pair_descriptor_distances(a: np.ndarray, b: np.ndarray, i: np.ndarray, j: np.ndarray) -> np.ndarray:
    """Euclidean distances ``||a[i] - b[j]||`` per pair (float32, as the inputs), in bounded-memory chunks.

    Uses ``||a - b||^2 = |a|^2 + |b|^2 - 2 a.b``: the pairs of a chunk (the k-d tree emits them leaf pair
    by leaf pair, so a chunk touches few distinct images) are looked up in one Gram matrix of its
    distinct rows, ``A @ B.T`` (``X @ X.T`` when ``a is b``), computed by BLAS; squared distances are
    clamped at 0 before the square root. Where the dot formula cancels -- the squared distance is below
    ``(|a|^2 + |b|^2) / 32``, i.e. near-duplicate descriptors -- and in chunks whose pairs touch too many
    distinct images, the distance is computed from the difference ``a[i] - b[j]`` instead. Both agree with
    the difference formula to float32 rounding (for unit-norm descriptors: at most about 3e-6, just above
    the cancellation threshold; the tests require 1e-5). The products run on one BLAS thread
    (:func:`vpr_nb._threads.single_threaded`): they are small, and extra threads stall on a busy machine.
    """
    out = np.empty(len(i), dtype=np.float32)
    if len(i) == 0:
        return out
    with single_threaded():
        _gram_distances_sq(a, b, i, j, out)
    return np.sqrt(out, out=out)


def _gram_distances_sq(a: np.ndarray, b: np.ndarray, i: np.ndarray, j: np.ndarray, out: np.ndarray) -> None:
    """The chunk loop of :func:`_pair_descriptor_distances`: squared distances into ``out``."""
    same = a is b
    na = np.einsum("ij,ij->i", a, a)
    nb = na if same else np.einsum("ij,ij->i", b, b)
    pos_a = np.empty(len(a), dtype=np.intp)
    pos_b = pos_a if same else np.empty(len(b), dtype=np.intp)
    chunk = _GRAM_CHUNK_PAIRS
    arange = np.arange(2 * chunk, dtype=np.intp)
    for s in range(0, len(i), chunk):
        ic, jc = i[s:s + chunk], j[s:s + chunk]
        k = len(ic)
        if same:
            u = _distinct(np.concatenate([ic, jc]), pos_a, arange)
            work = len(u) * len(u) // 2   # X @ X.T runs as a symmetric rank-k update
        else:
            ua, ub = _distinct(ic, pos_a, arange), _distinct(jc, pos_b, arange)
            work = len(ua) * len(ub)
        if work > _GRAM_MAX_WORK * k:   # scattered pairs: the Gram matrix would cost more than it saves
            out[s:s + k] = _direct_distances_sq(a, b, ic, jc)
            continue
        if same:
            x = a[u]
            gram, ncol = x @ x.T, len(u)
        else:
            gram, ncol = a[ua] @ b[ub].T, len(ub)
        ii, jj = pos_a[ic], pos_b[jc]
        scale = na[ic]
        scale += nb[jc]
        flat = ii * ncol
        flat += jj
        d2 = gram.ravel()[flat]
        d2 *= -2.0
        d2 += scale
        near = d2 < scale * _CANCEL_FRACTION
        if near.any():
            d2[near] = _direct_distances_sq(a, b, ic[near], jc[near])
        np.maximum(d2, 0.0, out=out[s:s + k])


def _bin_index(geo: np.ndarray | float, bin_width: float, num_bins: int) -> np.ndarray:
    """Bin of each geographic distance (the last bin is closed on the right), ``floor(geo / w)``
    capped at ``num_bins - 1``; arrays are done in blocks (no whole-array float temporary) into the
    smallest integer type that holds ``num_bins`` (one byte per pair for up to 127 bins)."""
    geo = np.asarray(geo)
    if geo.ndim == 0:
        return np.minimum(np.floor(geo / bin_width).astype(np.int64), num_bins - 1)
    dtype = np.int8 if num_bins <= 127 else np.int16 if num_bins <= 32767 else np.int64
    b = np.empty(geo.shape, dtype=dtype)
    for s in range(0, len(geo), _CHUNK_FLOATS):
        t = geo[s:s + _CHUNK_FLOATS] / bin_width
        np.floor(t, out=t)
        np.minimum(t, num_bins - 1, out=t)
        b[s:s + _CHUNK_FLOATS] = t
    return b


def _bin_moments(b: np.ndarray, values: np.ndarray, num_bins: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per-bin count, mean and population std of ``values``, in blocks (no whole-array temporary).

    The sums are accumulated pair after pair in float64 (``np.add.at``), as one ``np.bincount`` over the
    whole arrays would: the same bits, without its three whole-array float64/intp copies.
    """
    count = np.zeros(num_bins, dtype=np.int64)
    total = np.zeros(num_bins)
    for s in range(0, len(b), _CHUNK_FLOATS):
        bb = b[s:s + _CHUNK_FLOATS]
        count += np.bincount(bb, minlength=num_bins)
        np.add.at(total, bb, values[s:s + _CHUNK_FLOATS].astype(np.float64))
    squares = np.zeros(num_bins)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = total / count
        for s in range(0, len(b), _CHUNK_FLOATS):
            bb = b[s:s + _CHUNK_FLOATS]
            dev = values[s:s + _CHUNK_FLOATS] - mean[bb]   # float64, as desc - mean[b]
            dev *= dev
            np.add.at(squares, bb, dev)
        std = np.sqrt(squares / count)
    return count, mean, std


def _bin_value_keys(b: np.ndarray, values: np.ndarray, shift: int = 0) -> np.ndarray:
    """uint64 keys ``bin << (32 + shift) | bits(value) << shift`` (plus the position in the low
    ``shift`` bits when ``shift > 0``), whose order is (bin, value[, position]) for float32 values >= 0.

    The IEEE-754 bit pattern of a non-negative float32 read as uint32 is monotonic in the value, so
    sorting the keys sorts by bin, then by value, in one pass over 8-byte integers. Built in blocks,
    so the only whole-array allocation is the keys themselves.
    """
    bits = np.ascontiguousarray(values, dtype=np.float32).view(np.uint32)
    keys = np.empty(len(b), dtype=np.uint64)
    for s in range(0, len(b), _CHUNK_FLOATS):
        k = b[s:s + _CHUNK_FLOATS].astype(np.uint64)
        k <<= np.uint64(32 + shift)
        v = bits[s:s + _CHUNK_FLOATS].astype(np.uint64)
        if shift:
            v <<= np.uint64(shift)
            v |= np.arange(s, s + len(v), dtype=np.uint64)
        k |= v
        keys[s:s + _CHUNK_FLOATS] = k
    return keys


def _values_of_keys(keys: np.ndarray) -> np.ndarray:
    """The float32 values of sorted :func:`_bin_value_keys` keys (``shift=0``); the keys are overwritten."""
    keys &= np.uint64(0xFFFFFFFF)
    return keys.astype(np.uint32).view(np.float32)


def _sort_by_bin_then_value(b: np.ndarray, values: np.ndarray) -> np.ndarray:
    """Permutation sorting by bin, then by value (non-negative float32 values), ties by position.

    When ``bin | value bits | position`` fits in 64 bits (e.g. 256 bins and 16M pairs) the keys are
    sorted as values and the permutation is read from their low bits in place (no argsort); otherwise
    one argsort of the ``bin | value`` keys.
    """
    n = len(values)
    ib = max(1, (n - 1).bit_length())
    nb = int(b.max()).bit_length() if n else 0
    if 32 + ib + nb > 64:
        return np.argsort(_bin_value_keys(b, values))
    keys = _bin_value_keys(b, values, shift=ib)
    keys.sort()
    keys &= np.uint64((1 << ib) - 1)
    return keys.view(np.int64)


def _weighted_line(x: np.ndarray, y: np.ndarray, w: np.ndarray) -> tuple[float, float]:
    """Weighted least-squares ``y ~ intercept + slope * x``; returns ``(slope, intercept)``."""
    xm = np.average(x, weights=w)
    ym = np.average(y, weights=w)
    slope = float(np.sum(w * (x - xm) * (y - ym)) / np.sum(w * (x - xm) ** 2))
    return slope, float(ym - slope * xm)


def _quantile_positions(count: np.ndarray, q: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Where quantile ``q`` (numpy's "linear" method) of every bin lies in values sorted by (bin, value).

    Bin ``b`` occupies positions ``start_b .. start_b + count_b - 1``; its quantile is at the fractional
    position ``pos = start_b + q (count_b - 1)``, i.e. ``x[lo] (1 - frac) + x[hi] frac`` with
    ``lo = floor(pos)``, ``hi = min(lo + 1, start_b + count_b - 1)``, ``frac = pos - lo``.
    Returns ``(lo, hi, frac)``, meaningful for the non-empty bins only.
    """
    start = np.concatenate([[0], np.cumsum(count)[:-1]])
    pos = start + q * np.maximum(count - 1, 0)
    lo = np.floor(pos).astype(np.int64)
    hi = np.minimum(lo + 1, start + count - 1)
    return lo, hi, pos - lo


def _quantile_ranks(count: np.ndarray, qs: Sequence[float]) -> np.ndarray:
    """The sorted distinct positions (ranks in (bin, value) order) that :func:`_bin_quantiles` reads."""
    nonempty = count > 0
    ranks = [r[nonempty] for q in qs for r in _quantile_positions(count, q)[:2]]
    return np.unique(np.concatenate(ranks))


def _bin_quantiles(sorted_desc: np.ndarray, count: np.ndarray, qs: Sequence[float],
                   ranks: np.ndarray | None = None) -> dict[float, np.ndarray]:
    """Per-bin quantiles (numpy "linear" method) of values sorted by (bin, value).

    With ``ranks`` (the sorted positions of :func:`_quantile_ranks`), ``sorted_desc`` holds the sorted
    values at those positions only, ``sorted_desc[k]`` being the value at position ``ranks[k]``.
    """
    nonempty = count > 0
    out = {}
    for q in qs:
        lo, hi, frac = _quantile_positions(count, q)
        vals = np.full(len(count), np.nan)
        lo_n, hi_n, f_n = lo[nonempty], hi[nonempty], frac[nonempty]
        if ranks is not None:
            lo_n, hi_n = np.searchsorted(ranks, lo_n), np.searchsorted(ranks, hi_n)
        vals[nonempty] = sorted_desc[lo_n] * (1 - f_n) + sorted_desc[hi_n] * f_n
        out[float(q)] = vals
    return out


def _bin_order_statistics(b: np.ndarray, values: np.ndarray, count: np.ndarray,
                          qs: Sequence[float]) -> dict[float, np.ndarray]:
    """:func:`_bin_quantiles` without sorting all pairs: a one-level radix selection of the ranks it reads.

    Every pair falls in a bucket ``bin << S | bits(value) >> (31 - S)``: its bin, then the top ``S`` bits of
    its value's bit pattern (bit 31, the sign, is 0). The bit pattern of a non-negative float32 is monotonic
    in the value, so bucket numbers are monotonic in (bin, value): bucket ``c`` holds the positions
    ``cum[c] - hist[c] .. cum[c] - 1`` of the (bin, value) order, with ``hist`` the bucket counts and ``cum``
    their cumulative sum. The buckets holding the ranks of :func:`_quantile_ranks` are found from ``cum``;
    only their pairs are gathered, as :func:`_bin_value_keys` keys, and sorted. Rank ``r`` in bucket ``c``
    is then the key at ``offset_c + r - (cum[c] - hist[c])``, ``offset_c`` being where bucket ``c`` starts
    among the gathered keys: exactly the order statistic of a full sort. ``S`` is the largest width with
    at most :data:`_SELECT_BUCKETS` buckets and at most one bucket per two pairs (so the counts take at
    most 2 bytes per pair; 17 bits for 25 bins and 8.7M pairs: 512 buckets per power of two of the value),
    so the gathered pairs are a small fraction of all (all of them only if the values of a bin are nearly
    equal).
    """
    ranks = _quantile_ranks(count, qs)
    buckets = min(_SELECT_BUCKETS, max(len(b) // 2, len(count)))   # at most one bucket per two pairs
    shift = max(0, min(31, (buckets // len(count)).bit_length() - 1))   # S above
    values = np.ascontiguousarray(values, dtype=np.float32)
    bits = values.view(np.uint32)
    bucket_of = np.empty(len(b), dtype=np.int32)        # bucket of every pair (< 2**22)
    for s in range(0, len(b), _CHUNK_FLOATS):
        c = b[s:s + _CHUNK_FLOATS].astype(np.int32)
        c <<= shift
        c |= (bits[s:s + _CHUNK_FLOATS] >> np.uint32(31 - shift)).view(np.int32)
        bucket_of[s:s + _CHUNK_FLOATS] = c
    hist = np.zeros(len(count) << shift, dtype=np.int32 if len(b) < 2 ** 31 else np.int64)
    np.add.at(hist, bucket_of, hist.dtype.type(1))   # a one of hist's own type: numpy's fast path
    cum = np.cumsum(hist)
    rank_bucket = np.searchsorted(cum, ranks, side="right")   # bucket holding each rank
    wanted = np.unique(rank_bucket)
    is_wanted = np.zeros(len(hist), dtype=bool)
    is_wanted[wanted] = True
    picked = []
    for s in range(0, len(b), _CHUNK_FLOATS):
        sel = is_wanted[bucket_of[s:s + _CHUNK_FLOATS]]
        picked.append(_bin_value_keys(b[s:s + _CHUNK_FLOATS][sel], values[s:s + _CHUNK_FLOATS][sel]))
    del bucket_of
    keys = np.concatenate(picked)
    keys.sort()
    sizes = hist[wanted].astype(np.int64)
    offset = np.cumsum(sizes) - sizes                          # where each wanted bucket starts in keys
    at = offset[np.searchsorted(wanted, rank_bucket)] + ranks - (cum[rank_bucket] - hist[rank_bucket])
    return _bin_quantiles(_values_of_keys(keys[at]), count, qs, ranks)


MAX_BINS = 1_000_000   # bins a profile may have (each per-bin statistic is one float64 array of this length)


def gds_profile(descriptors, utm, max_distance: float, bin_width: float, pairs: str = "query-db", *,
                query_descriptors=None, query_utm=None, fit_range: tuple[float, float] = (0.0, 25.0),
                quantiles: Sequence[float] = (0.1, 0.5, 0.9), keep_pairs: bool = False) -> GDSProfile:
    """Bin every image pair by geographic distance and summarise its descriptor distance.

    Implements the GDS analysis behind Fig. 1 of CliqueMining (Izquierdo & Civera, ECCV 2024),
    with the pair set, bins, band and slope defined in the module docstring.

    Args:
        descriptors: ``(N, D)`` database descriptors (``pairs="query-db"``) or the image set
            (``pairs="all"``).
        utm: ``(N, 2)`` positions in metres, aligned with ``descriptors``.
        max_distance: largest geographic distance (m) of a pair that is kept.
        bin_width: width (m) of the geographic-distance bins; at most :data:`MAX_BINS` bins.
        pairs: ``"query-db"`` (needs ``query_descriptors`` and ``query_utm``) or ``"all"``.
        query_descriptors: ``(Q, D)`` query descriptors for ``pairs="query-db"``.
        query_utm: ``(Q, 2)`` query positions for ``pairs="query-db"``.
        fit_range: ``(lo, hi)`` metres; bins whose centre lies in it are used for the slope.
        quantiles: quantile levels in ``[0, 1]`` computed per bin.
        keep_pairs: store every pair's (geographic, descriptor) distance, needed by
            ``misordering_probability(..., method="empirical")``.

    Returns:
        A :class:`GDSProfile`.
    """
    if pairs not in _PAIR_MODES:
        raise ValueError(f"pairs must be one of {_PAIR_MODES}, got {pairs!r}")
    db = as_float_matrix(descriptors, "descriptors")
    db_utm = as_utm(utm, "utm")
    if len(db_utm) != len(db):
        raise ValueError(f"utm has {len(db_utm)} rows but descriptors has {len(db)}: give one position per image")
    max_distance = check_positive(max_distance, "max_distance")
    bin_width = check_positive(bin_width, "bin_width")
    if bin_width > max_distance:
        raise ValueError(f"bin_width ({bin_width}) must not exceed max_distance ({max_distance})")
    if max_distance / bin_width > MAX_BINS + 1e-9:
        raise ValueError(f"bin_width={bin_width:g} m over the range [0, {max_distance:g}] m asks for "
                         f"{max_distance / bin_width:.4g} bins, more than MAX_BINS={MAX_BINS}; use "
                         f"bin_width >= {max_distance / MAX_BINS:.3g} m")
    lo, hi = _check_fit_range(fit_range)
    qs = tuple(quantiles)
    for q in qs:
        if not (isinstance(q, (int, float, np.floating)) and 0.0 <= float(q) <= 1.0):
            raise ValueError(f"quantiles must be numbers in [0, 1], got {q!r}")
    if pairs == "query-db":
        if query_descriptors is None or query_utm is None:
            raise ValueError('pairs="query-db" needs query_descriptors and query_utm; '
                             'use pairs="all" to compare the images of one set with each other')
        qd = as_float_matrix(query_descriptors, "query_descriptors", dim=db.shape[1])
        q_utm = as_utm(query_utm, "query_utm")
        if len(q_utm) != len(qd):
            raise ValueError(f"query_utm has {len(q_utm)} rows but query_descriptors has {len(qd)}")
    else:
        if query_descriptors is not None or query_utm is not None:
            raise ValueError('pairs="all" uses only descriptors/utm; drop query_descriptors and query_utm '
                             'or use pairs="query-db"')
        if len(db) < 2:
            raise ValueError('pairs="all" needs at least two images')
        qd, q_utm = db, None

    i, j, geo = _geo_pairs(db_utm, q_utm, max_distance)
    if len(geo) == 0:
        raise ValueError(f"no image pair is within max_distance={max_distance} m; increase max_distance "
                         "or check that utm is in metres")
    desc = _pair_descriptor_distances(qd, db, i, j)
    del i, j

    num_bins = int(math.ceil(max_distance / bin_width - 1e-9))
    edges = bin_width * np.arange(num_bins + 1, dtype=np.float64)
    centers = 0.5 * (edges[:-1] + edges[1:])
    b = _bin_index(geo, bin_width, num_bins)
    if not keep_pairs:
        del geo       # only the bins are needed from here on
    count, mean, std = _bin_moments(b, desc, num_bins)

    pair_geo = pair_desc = None
    if keep_pairs:   # the pairs themselves are kept: sorted (bin, value, position) keys give the permutation
        order = _sort_by_bin_then_value(b, desc)
        del b
        pair_desc = desc[order]
        del desc
        pair_geo = geo[order]
        del geo, order
        quant = _bin_quantiles(pair_desc, count, qs) if qs else {}
    elif qs:         # only quantiles: select the ranks they read, no sort of all pairs
        quant = _bin_order_statistics(b, desc, count, qs)
        del b, desc
    else:
        quant = {}

    fit = (count > 0) & (centers >= lo) & (centers <= hi)
    if fit.sum() >= 2:
        slope, intercept = _weighted_line(centers[fit], mean[fit], count[fit].astype(np.float64))
    else:
        warnings.warn(f"fewer than two non-empty bins have their centre in fit_range={fit_range}; "
                      "slope and intercept are NaN", stacklevel=2)
        slope = intercept = float("nan")
    return GDSProfile(bin_edges=edges, bin_centers=centers, count=count, mean=mean, std=std,
                      quantiles=quant, slope=slope, intercept=intercept, pairs=pairs,
                      fit_range=(lo, hi),
                      pair_geo=pair_geo, pair_desc=pair_desc)


def _check_fit_range(fit_range) -> tuple[float, float]:
    try:
        lo, hi = (float(v) for v in fit_range)
    except (TypeError, ValueError):
        raise ValueError(f"fit_range must be a pair (lo, hi) of metres, got {fit_range!r}") from None
    if not (np.isfinite(lo) and np.isfinite(hi) and 0.0 <= lo < hi):
        raise ValueError(f"fit_range must satisfy 0 <= lo < hi (finite), got {fit_range!r}")
    return lo, hi


def _check_profile(profile) -> GDSProfile:
    if not isinstance(profile, GDSProfile):
        raise ValueError(f"profile must be a GDSProfile from gds_profile(), got {type(profile).__name__}")
    return profile


def _bin_of_distance(profile: GDSProfile, d, name: str) -> int:
    """Bin holding geographic distance ``d``; it must lie in the profile's range and be non-empty."""
    d = check_positive(d, name, allow_zero=True)
    if d > profile.bin_edges[-1]:
        raise ValueError(f"{name}={d} m is beyond the profile's last bin edge ({profile.bin_edges[-1]} m); "
                         "recompute the profile with a larger max_distance")
    b = int(_bin_index(d, profile.bin_width, len(profile.count)))
    if profile.count[b] == 0:
        raise ValueError(f"{name}={d} m falls in an empty bin [{profile.bin_edges[b]}, {profile.bin_edges[b + 1]}) "
                         "with no pairs; choose another distance or a wider bin_width")
    return b


def _prob_farther_ranked_first(profile: GDSProfile, b1: int, b2: int, method: str) -> float:
    """``P(D_2 < D_1)`` for descriptor distances of pairs from bins ``b1`` and ``b2``."""
    if method == "gaussian":
        dm = profile.mean[b1] - profile.mean[b2]
        s = math.sqrt(profile.std[b1] ** 2 + profile.std[b2] ** 2)
        if s == 0.0:
            return 0.5 if dm == 0 else float(dm > 0)
        return float(ndtr(dm / s))
    start = np.concatenate([[0], np.cumsum(profile.count)])
    x1 = profile.pair_desc[start[b1]:start[b1 + 1]]  # sorted within each bin
    x2 = profile.pair_desc[start[b2]:start[b2 + 1]]
    right = np.searchsorted(x1, x2, side="right")
    left = np.searchsorted(x1, x2, side="left")
    greater = np.sum(len(x1) - right, dtype=np.float64)
    ties = np.sum(right - left, dtype=np.float64)
    return float((greater + 0.5 * ties) / (len(x1) * len(x2)))


def _check_method(profile: GDSProfile, method: str) -> None:
    if method not in _METHODS:
        raise ValueError(f"method must be one of {_METHODS}, got {method!r}")
    if method == "empirical" and profile.pair_desc is None:
        raise ValueError('method="empirical" needs the raw pair distances: build the profile with '
                         'gds_profile(..., keep_pairs=True), or use method="gaussian"')


def misordering_probability(profile: GDSProfile, d1: float, d2: float, method: str = "gaussian") -> float:
    """Probability that a pair ``d2`` m apart looks more similar than a pair ``d1 < d2`` m apart.

    ``P(D(d2) < D(d1))`` with ``D`` the descriptor distance of a pair taken from the profile bin
    that contains each geographic distance. This is the probability of sorting two top-k
    retrievals at those distances in the wrong order (the quantity CliqueMining relates to GDS).

    Args:
        profile: a :class:`GDSProfile` (``keep_pairs=True`` for ``method="empirical"``).
        d1: geographic distance (m) of the nearer pair.
        d2: geographic distance (m) of the farther pair, ``d2 > d1``.
        method: ``"gaussian"``: ``Phi((mu1 - mu2) / sqrt(sigma1^2 + sigma2^2))`` from the bin
            means/stds; ``"empirical"``: the exact fraction of sample pairs ``(x1, x2)`` with
            ``x2 < x1`` (ties count 1/2), computed by sorting, O(n log n).
    """
    profile = _check_profile(profile)
    _check_method(profile, method)
    b1 = _bin_of_distance(profile, d1, "d1")
    b2 = _bin_of_distance(profile, d2, "d2")
    if not d1 < d2:
        raise ValueError(f"d1 must be smaller than d2 (d1 is the nearer pair), got d1={d1}, d2={d2}")
    return _prob_farther_ranked_first(profile, b1, b2, method)


def misordering_matrix(profile: GDSProfile, distances: Sequence[float], method: str = "gaussian") -> np.ndarray:
    """Matrix ``M[i, j] = P(D(distances[j]) < D(distances[i]))`` for a heatmap.

    For ``distances[i] < distances[j]`` the entry is :func:`misordering_probability`;
    ``M[j, i] = 1 - M[i, j]`` and the diagonal is 0.5.
    """
    profile = _check_profile(profile)
    _check_method(profile, method)
    ds = np.asarray(distances, dtype=np.float64)
    if ds.ndim != 1 or len(ds) == 0:
        raise ValueError(f"distances must be a non-empty 1-D list of metres, got shape {ds.shape}")
    bins = [_bin_of_distance(profile, d, f"distances[{k}]") for k, d in enumerate(ds)]
    n = len(bins)
    out = np.empty((n, n))
    for a in range(n):
        for c in range(n):
            out[a, c] = _prob_farther_ranked_first(profile, bins[a], bins[c], method)
    return out


def _order_stats(geo: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per row of ``(Q, k)`` geo distances in rank order: fraction of correct pairs and tau-b."""
    iu, ju = np.triu_indices(geo.shape[1], 1)  # pairs (a, b) with a ranked before b
    n0 = len(iu)
    concordant = np.empty(len(geo), dtype=np.int64)
    discordant = np.empty(len(geo), dtype=np.int64)
    chunk = max(1, _CHUNK_FLOATS // n0)
    for s in range(0, len(geo), chunk):
        sign = np.sign(geo[s:s + chunk, ju] - geo[s:s + chunk, iu])
        concordant[s:s + chunk] = (sign > 0).sum(axis=1)
        discordant[s:s + chunk] = (sign < 0).sum(axis=1)
    ties = n0 - concordant - discordant
    fraction = (concordant + ties) / n0
    with np.errstate(invalid="ignore", divide="ignore"):
        tau = (concordant - discordant) / np.sqrt(n0 * (n0 - ties).astype(np.float64))
    return fraction, tau


@single_threaded_call
def topk_order_agreement(q_desc, db_desc, q_utm, db_utm, k: int = 10) -> OrderAgreement:
    """Are the top-k retrievals of each query sorted by geographic distance?

    Retrieves the ``k`` nearest database descriptors of every query (exact L2 search,
    ``faiss.IndexFlatL2``). For each query, a pair of retrievals ``(a, b)`` with ``a`` ranked
    before ``b`` is *correctly ordered* when ``geo(a) <= geo(b)``. Reports the fraction of
    correctly ordered pairs and Kendall's tau-b between the retrieval rank and the geographic
    distance (+1: perfectly sorted by distance, -1: reversed). This is the top-k sorting that
    CliqueMining ties to the Geographic Distance Sensitivity.
    """
    qd, dbd, qu, du = check_geo_descriptors(q_desc, db_desc, q_utm, db_utm)
    k = check_int(k, "k", minimum=2, maximum=len(dbd))
    index = faiss.IndexFlatL2(dbd.shape[1])
    index.add(dbd)
    _, topk = index.search(qd, k)
    topk = topk.astype(np.int64)
    geo = np.sqrt(((du[topk] - qu[:, None, :]) ** 2).sum(axis=2))
    fraction, tau = _order_stats(geo)
    finite = np.isfinite(tau)
    return OrderAgreement(topk=topk, topk_geo=geo, fraction_correct=fraction, kendall_tau=tau,
                          mean_fraction_correct=float(fraction.mean()),
                          mean_kendall_tau=float(tau[finite].mean()) if finite.any() else float("nan"))


@dataclass(frozen=True, eq=False)
class QueryTopK:
    """The top-k retrievals of one query with their true geographic distances.

    Attributes:
        query: the query index.
        db_index: ``(k,)`` database indices, nearest descriptor first.
        desc_distance: ``(k,)`` Euclidean descriptor distances.
        geo_distance: ``(k,)`` geographic distances (m) from the query.
        is_positive: ``(k,)`` True where ``geo_distance <= pos_radius`` (all False without a radius).
        fraction_correct: fraction of retrieval pairs ``(a, b)``, ``a`` ranked before ``b``, with
            ``geo(a) <= geo(b)`` (as in :func:`topk_order_agreement`).
    """

    query: int
    db_index: np.ndarray
    desc_distance: np.ndarray
    geo_distance: np.ndarray
    is_positive: np.ndarray
    fraction_correct: float

    def table(self) -> str:
        """The retrievals as a fixed-width text table (rank, db index, descriptor and geographic distance)."""
        lines = [f"query {self.query}: {self.fraction_correct:.3f} of the top-{len(self.db_index)} pairs sorted by distance",
                 "rank  db index  desc dist  geo dist (m)  positive"]
        for r, (i, dd, g, p) in enumerate(zip(self.db_index, self.desc_distance, self.geo_distance, self.is_positive)):
            lines.append(f"{r + 1:>4}  {i:>8}  {dd:>9.3f}  {g:>12.1f}  {'yes' if p else 'no':>8}")
        return "\n".join(lines)


def query_topk(q_desc, db_desc, q_utm, db_utm, query: int, k: int = 5, pos_radius: float | None = None) -> QueryTopK:
    """Top-k database images of query ``query`` by descriptor distance, with their geographic distances.

    The pure function behind the notebook's query-picker widget: exact Euclidean search (ties
    broken by database index), then the true distance of every retrieval and whether the top-k is
    sorted by it (CliqueMining's "close, but not there": the nearest image should come first).
    """
    qd, dbd, qu, du = check_geo_descriptors(q_desc, db_desc, q_utm, db_utm)
    query = check_int(query, "query", minimum=0, maximum=len(qd) - 1)
    k = check_int(k, "k", minimum=1, maximum=len(dbd))
    if pos_radius is not None:
        pos_radius = check_positive(pos_radius, "pos_radius")
    diff = dbd.astype(np.float64) - qd[query].astype(np.float64)
    desc = np.sqrt(np.einsum("ij,ij->i", diff, diff))
    top = np.argsort(desc, kind="stable")[:k]
    geo = np.sqrt(((du[top] - qu[query]) ** 2).sum(axis=1))
    if k >= 2:
        fraction = float(_order_stats(geo[None])[0][0])
    else:
        fraction = 1.0
    pos = np.zeros(k, dtype=bool) if pos_radius is None else geo <= pos_radius
    return QueryTopK(query=query, db_index=top.astype(np.int64), desc_distance=desc[top], geo_distance=geo,
                     is_positive=pos, fraction_correct=fraction)
