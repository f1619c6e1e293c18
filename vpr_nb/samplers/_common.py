"""Shared pieces of the samplers: input checks, seeds and the group index (images of each place group).

Every sampler takes a ``seed`` or a ``np.random.Generator`` and returns the same output for the same
seed. Distances between geotags are Euclidean distances of UTM (easting, northing) in metres.
"""
from __future__ import annotations

import numpy as np

_CHUNK = 1 << 16       # elements per temporary in the blockwise loops (bounded memory)


def _as_groups(groups, n: int | None) -> np.ndarray:
    """Validate a 1-D array of non-negative integer group ids (one per image)."""
    arr = np.asarray(groups)
    if arr.ndim != 1:
        raise ValueError(f"groups must be a 1-D array with one place-group id per image, got shape {arr.shape}")
    if len(arr) == 0:
        raise ValueError("groups is empty: give one place-group id per image")
    if not np.issubdtype(arr.dtype, np.integer):
        raise ValueError(f"groups must hold integers (place-group ids), got dtype {arr.dtype}")
    if arr.min() < 0:
        raise ValueError(f"groups must be non-negative ids, found {int(arr.min())}")
    if n is not None and len(arr) != n:
        raise ValueError(f"groups has {len(arr)} entries but utm has {n} rows: give one group id per image")
    return arr.astype(np.int64, copy=False)   # no copy of int64 ids (the index never writes to them)


def _seed_sequences(seed, n: int) -> list[np.random.SeedSequence]:
    """One independent SeedSequence per batch, derived from an int seed or a Generator."""
    if isinstance(seed, np.random.Generator):
        seed = int(seed.integers(2**63))
    elif isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"seed must be a non-negative int or a np.random.Generator, got {seed!r}")
    return np.random.SeedSequence(int(seed)).spawn(n)


def _as_rng(rng) -> np.random.Generator:
    if isinstance(rng, np.random.Generator):
        return rng
    if isinstance(rng, (int, np.integer)) and not isinstance(rng, bool) and rng >= 0:
        return np.random.default_rng(int(rng))
    raise ValueError(f"rng must be a np.random.Generator (or a non-negative int seed), got {rng!r}")


def _dist(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Euclidean distance of broadcastable (..., 2) UTM arrays, in metres."""
    return np.sqrt(((a - b) ** 2).sum(axis=-1))


def _group_index(groups: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(order, starts)``: the images of group ``g`` are ``order[starts[g]:starts[g + 1]]``.

    ``order`` is ``np.argsort(groups, kind="stable")`` (images of a group in ascending index), built
    as a counting sort over blocks of ``_CHUNK`` images, so no temporary has the size of the data set;
    it is int32 when the indices fit (half the memory of int64).
    """
    counts = np.bincount(groups)
    starts = np.zeros(len(counts) + 1, dtype=np.int64)
    np.cumsum(counts, out=starts[1:])
    order = np.empty(len(groups), dtype=np.int32 if len(groups) < 2**31 else np.int64)
    cursor = starts[:-1].copy()   # next free slot of each group in ``order``
    for s in range(0, len(groups), _CHUNK):
        g = groups[s:s + _CHUNK]
        o = np.argsort(g, kind="stable")          # the block's images, by group, ascending within a group
        gs = g[o]
        run = np.flatnonzero(np.concatenate([[True], gs[1:] != gs[:-1]]))   # first position of each group
        lens = np.diff(np.append(run, len(gs)))
        ids = gs[run]
        order[np.repeat(cursor[ids] - run, lens) + np.arange(len(gs))] = o + s
        cursor[ids] += lens
    return order, starts

