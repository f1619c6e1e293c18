"""Deterministic pseudo-random numbers per element from integer coordinates (an FNV-style hash), so that a
world's details (lit windows, leaves, grass patches) are the same wherever and in whatever order they are drawn."""
from __future__ import annotations

import numpy as np


def hash01(*ints) -> np.ndarray:
    """Deterministic per-element pseudo random numbers in [0, 1) from integer arrays."""
    h = np.uint64(1469598103934665603)
    out = np.full(np.broadcast(*ints).shape, h, dtype=np.uint64)
    for x in ints:
        out ^= np.asarray(x).astype(np.int64).astype(np.uint64)
        out *= np.uint64(1099511628211)
        out ^= out >> np.uint64(29)
    return (out % np.uint64(1 << 24)).astype(np.float64) / float(1 << 24)
