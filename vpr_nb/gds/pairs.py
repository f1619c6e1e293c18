"""The image pairs of a GDS profile and their two distances: geographic (UTM) and descriptor (Euclidean).

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
"""
from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from .._threads import single_threaded

_CHUNK_FLOATS = 1 << 17  # floats per temporary (512 KiB, cache-sized) in the chunked loops (of the whole package)
_DESC_CHUNK_FLOATS = 1 << 18  # floats per gathered descriptor block (1 MiB)
_GRAM_CHUNK_PAIRS = 8192  # pairs per Gram-matrix lookup in _pair_descriptor_distances
_GRAM_MAX_WORK = 24  # Gram entries (symmetric: half) per pair above which a chunk uses the difference formula
                     # (a gathered-difference chunk costs about as much as a Gram matrix of ~35 entries per pair)
_CANCEL_FRACTION = np.float32(1 / 32)  # d^2 < (|a|^2 + |b|^2) * this: recompute from the difference


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
