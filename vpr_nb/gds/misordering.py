"""Mis-ordering probability: how likely a GDS profile ranks an image farther away before a nearer one.

Mis-ordering probability
    ``P(D(d2) < D(d1))`` for ``d1 < d2``: the probability that a pair taken ``d2`` metres apart
    gets a *smaller* descriptor distance than a pair taken ``d1`` metres apart, so that the farther
    image is ranked first. ``"gaussian"`` models each bin as a normal distribution,
    ``Phi((mu1 - mu2) / sqrt(sigma1^2 + sigma2^2))``; ``"empirical"`` compares every sample of the
    two bins exactly (ties count one half).
"""
from __future__ import annotations

import math
from typing import Sequence

import numpy as np
from scipy.special import ndtr

from .._checks import check_positive
from .binning import _bin_index
from .profile import GDSProfile

_METHODS = ("gaussian", "empirical")


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
