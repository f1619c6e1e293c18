"""How close and how alike the places of a batch are: :func:`batch_statistics` (CliqueMining vs random)."""
from __future__ import annotations

import numpy as np

from .._checks import as_float_matrix, as_utm
from ._common import _dist


def batch_statistics(batches, utm, descriptors=None) -> dict:
    """How close and how alike the places of batches are (the point of CliqueMining).

    For every batch ``(P, K)`` and every pair of its places: the distance between the place centres
    (mean UTM of the K images) and, with ``descriptors`` (one row per image, L2-normalised), the
    cosine similarity of the place descriptors (mean of the K image descriptors, L2-normalised).

    Returns:
        A dict of medians over all pairs of all batches: ``"median place distance (m)"``, ``"median place
        similarity"`` (NaN without descriptors) and ``"cities per batch"`` (the last key is absent).
    """
    b = np.asarray(batches)
    if b.ndim == 2:
        b = b[None]
    if b.ndim != 3 or b.shape[1] < 2:
        raise ValueError(f"batches must have shape (B, P, K) with P >= 2, got {b.shape}")
    u = as_utm(utm, "utm")
    iu = np.triu_indices(b.shape[1], 1)
    centre = u[b].mean(axis=2)                                             # (B, P, 2)
    dist = _dist(centre[:, :, None, :], centre[:, None, :, :])[:, iu[0], iu[1]]
    out = {"median place distance (m)": float(np.median(dist)), "median place similarity": float("nan")}
    if descriptors is not None:
        x = as_float_matrix(descriptors, "descriptors")[b].mean(axis=2)    # (B, P, D)
        x /= np.maximum(np.linalg.norm(x, axis=-1, keepdims=True), 1e-12)
        sim = np.einsum("bpd,bqd->bpq", x, x)[:, iu[0], iu[1]]
        out["median place similarity"] = float(np.median(sim))
    return out
