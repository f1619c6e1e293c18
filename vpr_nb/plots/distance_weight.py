"""DW-T-Loss's geographic weight as a picture: Eq. (4) against distance and distance rank, beside T-Loss's 1.

:func:`plot_distance_weight` draws the weights of a batch's query-positive pairs (notebook 03); it calls no random
generator, so a notebook's random streams are left as they were.
"""
from __future__ import annotations

import matplotlib.pyplot as plt
import numpy as np

from .._checks import check_positive
from ..losses import distance_weight
from ._inputs import as_numbers


def plot_distance_weight(geo_qp, weights, sigma: float, eps: float, axes=None):
    """The weight of Eq. (4), w = (1 + eps) / (g_qp / sigma + eps) - 1, of a batch's pairs, and T-Loss's flat 1.

    ``geo_qp``: the query-positive distances in metres (B,); ``weights``: their Eq. (4) weights (B,), e.g.
    ``vpr_nb.losses.distance_weight(geo_qp, sigma, eps)``; numpy arrays or torch tensors. A ValueError if the
    weights are not Eq. (4) of ``geo_qp`` at this ``sigma`` and ``eps``. Left: the curve of Eq. (4) on a log
    distance axis with the batch's pairs on it, sigma marked (w = 0 there, negative beyond), and T-Loss's weight
    1 (every triplet counts the same). Right: each pair's weight by the rank of its distance (1 = nearest
    positive) beside T-Loss's 1, so W-T-Loss reads as T-Loss times about the mean weight. Two axes may be given
    in ``axes``; returns the figure.
    """
    pair = "one per query-positive pair"
    geo, w = as_numbers(geo_qp, "geo_qp", 1, pair), as_numbers(weights, "weights", 1, pair)
    if len(w) != len(geo):
        raise ValueError(f"weights has {len(w)} values for {len(geo)} distances: give one weight per pair")
    if (geo < 0).any():
        raise ValueError("geo_qp must be distances in metres (>= 0), got a negative value")
    sigma, eps = check_positive(sigma, "sigma"), check_positive(eps, "eps")
    expected = distance_weight(geo, sigma, eps)
    if not np.allclose(w, expected, rtol=1e-4, atol=1e-4):
        raise ValueError(f"weights are not Eq. (4) of geo_qp at sigma = {sigma:g}, eps = {eps:g} (largest gap "
                         f"{np.abs(w - expected).max():.3g}): pass the sigma and eps the weights were computed with")
    if axes is None:
        _, axes = plt.subplots(1, 2, figsize=(11, 3.8))
    if len(axes) != 2:
        raise ValueError(f"axes must be two matplotlib axes (the curve, the ranks), got {len(axes)}")
    _curve(axes[0], geo, w, sigma, eps)
    _ranks(axes[1], geo, w)
    fig = axes[0].figure
    fig.tight_layout()
    return fig


def _curve(ax, geo, w, sigma, eps):
    positive = geo[geo > 0]
    lo = min(1.0, 0.5 * positive.min()) if len(positive) else 1.0
    grid = np.geomspace(lo, 2.5 * max(sigma, geo.max()), 400)
    ax.plot(grid, distance_weight(grid, sigma, eps), color="tab:purple", label="w, Eq. (4)")
    ax.scatter(np.maximum(geo, lo), w, color="tab:purple", edgecolors="k", zorder=3,
               label=f"the batch's {len(geo)} positives")
    ax.axhline(1.0, color="tab:blue", ls="--", label="T-Loss: w = 1 for every triplet")
    ax.axhline(0.0, color="0.6", lw=0.8)
    ax.axvline(sigma, color="tab:red", ls=":", label=f"σ = {sigma:g} m: w = 0")
    ax.set_xscale("log")
    ax.set(xlabel="query-positive distance g_qp (m, log scale)", ylabel="weight of the triplet",
           title=f"Eq. (4) at σ = {sigma:g} m, ε = {eps:g}")
    ax.legend(fontsize=7, loc="upper right")


def _ranks(ax, geo, w):
    order = np.argsort(geo, kind="stable")
    rank = np.arange(1, len(geo) + 1)
    ax.bar(rank, w[order], color="tab:purple", alpha=0.8, label="W-T / DW-T weight, Eq. (4)")
    ax.axhline(1.0, color="tab:blue", ls="--", label="T-Loss weight (1)")
    if len(geo) <= 16:
        for r, i in zip(rank, order):
            ax.annotate(f"{geo[i]:.1f} m", (r, w[i]), textcoords="offset points", xytext=(0, 3), ha="center",
                        fontsize=7)
    ax.set(xlabel="rank of the positive's distance (1 = nearest)", ylabel="weight of the triplet",
           title=f"by distance rank: mean w = {w.mean():.2f}, from {w.min():.2f} to {w.max():.2f}")
    ax.set_ylim(min(0.0, w.min() * 1.1), max(1.0, w.max()) * 1.35)
    ax.legend(fontsize=7, loc="upper right", ncol=2)
