"""Earlier implementations of ``vpr_nb.gds.gds_profile``, kept as the baselines of bench/bench_gds.py.

* :func:`previous_gds_profile` -- before issue 12: whole-array temporaries and an argsort of the
  descriptor distances, then a stable argsort of the bins.
* :func:`first_pass_gds_profile` -- issue 12's first pass (commit 43078cd): chunked geo distances from
  ``(P, 2)`` row gathers, no argsort (sorted uint64 ``bin | value`` keys), descriptor distances from two
  gathered blocks per 512 pairs.

Both compute ``gds_profile(db, utm, max_distance, bin_width, pairs="all", quantiles=(0.1, 0.5, 0.9))``
without input validation and return ``dict(count, mean, std, quantiles, slope, intercept, pair_geo,
pair_desc)``; the bench checks that the current implementation returns the same bin counts and, up to
float32 rounding of the descriptor distances (it computes them from dot products), the same values.
"""
from __future__ import annotations

import math

import numpy as np
from scipy.spatial import cKDTree

_CHUNK_FLOATS = 1 << 17


def _descriptor_distances(a, b, i, j):
    """Descriptor distances as both baselines computed them (512-pair blocks for 256-D)."""
    out = np.empty(len(i), dtype=np.float32)
    chunk = max(1, _CHUNK_FLOATS // a.shape[1])
    for s in range(0, len(i), chunk):
        diff = a[i[s:s + chunk]] - b[j[s:s + chunk]]
        out[s:s + chunk] = np.sqrt(np.einsum("ij,ij->i", diff, diff))
    return out


def _bin_index(geo, bin_width, num_bins):
    return np.minimum(np.floor(np.asarray(geo) / bin_width).astype(np.int64), num_bins - 1)


def _bin_quantiles(sorted_desc, count, qs):
    start = np.concatenate([[0], np.cumsum(count)[:-1]])
    nonempty = count > 0
    out = {}
    for q in qs:
        pos = start + q * np.maximum(count - 1, 0)
        lo = np.floor(pos).astype(np.int64)
        hi = np.minimum(lo + 1, start + count - 1)
        frac = pos - lo
        vals = np.full(len(count), np.nan)
        vals[nonempty] = sorted_desc[lo[nonempty]] * (1 - frac[nonempty]) + sorted_desc[hi[nonempty]] * frac[nonempty]
        out[float(q)] = vals
    return out


def _weighted_line(x, y, w):
    xm = np.average(x, weights=w)
    ym = np.average(y, weights=w)
    slope = float(np.sum(w * (x - xm) * (y - ym)) / np.sum(w * (x - xm) ** 2))
    return slope, float(ym - slope * xm)


def _fit(count, mean, centers, fit):
    f = (count > 0) & (centers >= fit[0]) & (centers <= fit[1])
    return _weighted_line(centers[f], mean[f], count[f].astype(np.float64))


def previous_gds_profile(db, utm, max_distance, bin_width, keep_pairs, qs=(0.1, 0.5, 0.9), fit=(0.0, 25.0)):
    """gds_profile(pairs="all") as it was before issue 12."""
    ij = cKDTree(utm).query_pairs(max_distance, output_type="ndarray")
    i, j = ij[:, 0].astype(np.int64), ij[:, 1].astype(np.int64)
    geo = np.sqrt(((utm[i] - utm[j]) ** 2).sum(axis=1))
    keep = geo <= max_distance
    i, j, geo = i[keep], j[keep], geo[keep]
    desc = _descriptor_distances(db, db, i, j)
    del i, j
    num_bins = int(math.ceil(max_distance / bin_width - 1e-9))
    centers = bin_width * (np.arange(num_bins) + 0.5)
    b = _bin_index(geo, bin_width, num_bins)
    count = np.bincount(b, minlength=num_bins)
    mean = np.bincount(b, weights=desc, minlength=num_bins) / count
    std = np.sqrt(np.bincount(b, weights=(desc - mean[b]) ** 2, minlength=num_bins) / count)
    order = np.argsort(desc)
    order = order[np.argsort(b.astype(np.int16)[order], kind="stable")]
    quant = _bin_quantiles(desc[order], count, qs)
    slope, intercept = _fit(count, mean, centers, fit)
    return dict(count=count, mean=mean, std=std, quantiles=quant, slope=slope, intercept=intercept,
                pair_geo=geo[order] if keep_pairs else None, pair_desc=desc[order] if keep_pairs else None)


def _first_pass_sort_by_bin_then_value(b, values):
    n = len(values)
    ib = max(1, (n - 1).bit_length())
    nb = int(b.max()).bit_length() if n else 0
    if 32 + ib + nb > 64:
        keys = b.astype(np.uint64)
        keys <<= np.uint64(32)
        keys |= np.ascontiguousarray(values, dtype=np.float32).view(np.uint32)
        return np.argsort(keys)
    keys = b.astype(np.uint64)
    keys <<= np.uint64(32 + ib)
    bits = np.ascontiguousarray(values, dtype=np.float32).view(np.uint32).astype(np.uint64)
    bits <<= np.uint64(ib)
    keys |= bits
    del bits
    keys |= np.arange(n, dtype=np.uint64)
    keys.sort()
    keys &= np.uint64((1 << ib) - 1)
    return keys.astype(np.int64)


def first_pass_gds_profile(db, utm, max_distance, bin_width, keep_pairs, qs=(0.1, 0.5, 0.9), fit=(0.0, 25.0)):
    """gds_profile(pairs="all") as of commit 43078cd (issue 12's first pass)."""
    ij = cKDTree(utm).query_pairs(max_distance, output_type="ndarray")
    i, j = ij[:, 0].astype(np.int64), ij[:, 1].astype(np.int64)
    geo = np.empty(len(i), dtype=np.float64)
    step = max(1, _CHUNK_FLOATS // 2)
    for s in range(0, len(i), step):
        diff = utm[i[s:s + step]] - utm[j[s:s + step]]
        np.square(diff, out=diff)
        geo[s:s + step] = np.sqrt(diff.sum(axis=1))
    keep = geo <= max_distance
    if not keep.all():
        i, j, geo = i[keep], j[keep], geo[keep]
    desc = _descriptor_distances(db, db, i, j)
    del i, j
    num_bins = int(math.ceil(max_distance / bin_width - 1e-9))
    centers = bin_width * (np.arange(num_bins) + 0.5)
    b = _bin_index(geo, bin_width, num_bins)
    count = np.bincount(b, minlength=num_bins)
    mean = np.bincount(b, weights=desc, minlength=num_bins) / count
    dev = desc - mean[b]
    np.square(dev, out=dev)
    std = np.sqrt(np.bincount(b, weights=dev, minlength=num_bins) / count)
    del dev
    order = None
    if keep_pairs:
        order = _first_pass_sort_by_bin_then_value(b, desc)
        sorted_desc = desc[order]
    else:
        keys = b.astype(np.uint64)
        keys <<= np.uint64(32)
        keys |= np.ascontiguousarray(desc, dtype=np.float32).view(np.uint32)
        keys.sort()
        sorted_desc = (keys & np.uint64(0xFFFFFFFF)).astype(np.uint32).view(np.float32)
        del keys
    quant = _bin_quantiles(sorted_desc, count, qs)
    slope, intercept = _fit(count, mean, centers, fit)
    return dict(count=count, mean=mean, std=std, quantiles=quant, slope=slope, intercept=intercept,
                pair_geo=geo[order] if keep_pairs else None, pair_desc=sorted_desc if keep_pairs else None)
