"""Binned order statistics of the pair distances: per-bin count, mean, std and quantiles, in bounded memory.

Bins
    ``B = ceil(max_distance / bin_width)`` bins of width ``bin_width`` starting at 0 m:
    bin ``b`` holds pairs with geographic distance in ``[b*w, (b+1)*w)``; the last bin is closed
    and also holds pairs at exactly ``max_distance``. ``bin_centers = (b + 0.5) * w``.
Per-bin statistics
    ``count``, ``mean`` and population standard deviation ``std`` (ddof = 0) of the descriptor
    distance, and the requested ``quantiles`` (numpy's ``"linear"`` method). Empty bins hold NaN.
"""
from __future__ import annotations

from typing import Sequence

import numpy as np

from .pairs import _CHUNK_FLOATS

_SELECT_BUCKETS = 1 << 22  # most (bin, value) buckets of the quantile selection (_bin_order_statistics; 16 MiB of counts)


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
