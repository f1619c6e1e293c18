"""The GDS profile: :func:`gds_profile` bins every image pair by geographic distance and fits the slope.

The pair set and distances are defined in :mod:`vpr_nb.gds.pairs`, the bins and per-bin statistics in
:mod:`vpr_nb.gds.binning`; this module adds:

Band
    the plot shades ``mean +- 1 std``.
Slope (units: descriptor-distance units per metre)
    weighted least-squares line ``mean_b ~ intercept + slope * center_b`` over the non-empty bins
    whose centre lies in ``fit_range`` (inclusive), with weights ``count_b``. This equals the
    ordinary least-squares fit over the raw pairs with each geographic distance replaced by its
    bin centre. A larger slope means the embedding separates near from far places better, i.e.
    a higher geographic distance sensitivity.
"""
from __future__ import annotations

import math
import warnings
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from .._checks import as_float_matrix, as_utm, check_positive
from .binning import _bin_index, _bin_moments, _bin_order_statistics, _bin_quantiles, _sort_by_bin_then_value
from .pairs import _geo_pairs, _pair_descriptor_distances

_PAIR_MODES = ("query-db", "all")


@dataclass(frozen=True, eq=False)
class GDSProfile:
    """Descriptor distance as a function of geographic distance (see :mod:`vpr_nb.gds`).

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


def _weighted_line(x: np.ndarray, y: np.ndarray, w: np.ndarray) -> tuple[float, float]:
    """Weighted least-squares ``y ~ intercept + slope * x``; returns ``(slope, intercept)``."""
    xm = np.average(x, weights=w)
    ym = np.average(y, weights=w)
    slope = float(np.sum(w * (x - xm) * (y - ym)) / np.sum(w * (x - xm) ** 2))
    return slope, float(ym - slope * xm)


MAX_BINS = 1_000_000   # bins a profile may have (each per-bin statistic is one float64 array of this length)


def gds_profile(descriptors, utm, max_distance: float, bin_width: float, pairs: str = "query-db", *,
                query_descriptors=None, query_utm=None, fit_range: tuple[float, float] = (0.0, 25.0),
                quantiles: Sequence[float] = (0.1, 0.5, 0.9), keep_pairs: bool = False) -> GDSProfile:
    """Bin every image pair by geographic distance and summarise its descriptor distance.

    Implements the GDS analysis behind Fig. 1 of CliqueMining (Izquierdo & Civera, ECCV 2024),
    with the pair set defined in :mod:`vpr_nb.gds.pairs`, the bins in :mod:`vpr_nb.gds.binning`, the band
    and slope in the module docstring.

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
