"""A CliqueMining batch on the map beside a random-place batch: which places one training batch holds, and where.

:func:`plot_clique_batches` draws the places of a clique batch (Eqs. (1)-(2) of notebook 07) and of a random-place
batch (GSV-Cities) over the same map; it calls no random generator, so a notebook's random streams are left as they
were.
"""
from __future__ import annotations

import matplotlib.pyplot as plt
import numpy as np


def _batch(batch, n: int, name: str) -> np.ndarray:
    b = batch.detach().cpu().numpy() if hasattr(batch, "detach") else np.asarray(batch)
    if b.ndim != 2 or 0 in b.shape or not np.issubdtype(b.dtype, np.integer):
        raise ValueError(f"{name} must be one batch, a (P, K) integer array of image indices (one row per place), "
                         f"got {b.dtype} of shape {b.shape}; from (num_batches, P, K) batches pass batches[0]")
    if b.min() < 0 or b.max() >= n:
        raise ValueError(f"{name} indexes images {int(b.min())}..{int(b.max())} but utm has {n} rows")
    return b


def _median_centre_distance(utm: np.ndarray, batch: np.ndarray) -> float:
    centres = utm[batch].mean(axis=1)                                    # (P, 2): one centre per place
    d = np.linalg.norm(centres[:, None] - centres[None], axis=-1)
    return float(np.median(d[np.triu_indices(len(centres), 1)])) if len(centres) > 1 else 0.0


def plot_clique_batches(utm, clique_batch, random_batch, axes=None, threshold: float | None = None):
    """One clique batch beside one random-place batch, on the same map (notebook 07, Eqs. (1)-(2)).

    ``utm``: (N, 2) positions in metres of the images the batches index (the map, drawn faint); ``clique_batch``
    and ``random_batch``: one batch each, (P, K) image indices, one row per place, e.g. ``clique_batches(...)[0]``
    and ``random_place_batches(...)[0]`` (or a batch of ``CliqueBatchMaker`` / ``RandomPlaceBatches``);
    ``threshold``: the same-place threshold tau of Eq. (2) in metres, for the titles. Each panel draws every image
    of the map in light grey and the K images of every place of its batch in one colour per place, with the median distance between the place centres: the clique batch's places are
    similar groups of one area (Eq. 1), cliques of the graph of Eq. (2), each >= tau from the others; the random
    batch's are drawn uniformly over the whole map. The two panels share their axes (stacked when the map is
    more than twice as wide as it is tall). Two axes may be given in ``axes``; returns the figure.
    """
    xy = utm.detach().cpu().numpy() if hasattr(utm, "detach") else np.asarray(utm)
    if xy.ndim != 2 or xy.shape[1] != 2 or len(xy) == 0 or not np.issubdtype(xy.dtype, np.number):
        raise ValueError(f"utm must be (N, 2) positions in metres (easting, northing), got shape {xy.shape}")
    xy = xy.astype(np.float64)
    if not np.isfinite(xy).all():
        raise ValueError("utm contains NaN or inf")
    batches = {"clique batch": _batch(clique_batch, len(xy), "clique_batch"),
               "random batch": _batch(random_batch, len(xy), "random_batch")}
    if threshold is not None and not (isinstance(threshold, (int, float, np.floating)) and threshold > 0):
        raise ValueError(f"threshold must be a positive distance in metres, got {threshold!r}")
    span = np.ptp(xy, axis=0) + 1e-9
    wide = span[0] > 2 * span[1]
    if axes is None:
        shape, size = ((2, 1), (12, 2 + 2 * min(3.0, 12 * span[1] / span[0]))) if wide else ((1, 2), (12, 5.5))
        _, axes = plt.subplots(*shape, figsize=size, sharex=True, sharey=True, layout="constrained")
    if len(axes) != 2:
        raise ValueError(f"axes must be two matplotlib axes (clique batch, random batch), got {len(axes)}")
    cmap = plt.get_cmap("tab20")
    for ax, (name, b) in zip(axes, batches.items()):
        ax.scatter(*xy.T, s=2, color="0.85", zorder=0)
        for p, place in enumerate(b):
            colour, pts = cmap(p % cmap.N), xy[place]
            ax.scatter(*pts.T, s=30, color=colour, edgecolor="k", lw=0.4, zorder=2)
        tau = f", each place >= tau = {threshold:g} m from the others" if threshold and name == "clique batch" else ""
        ax.set_title(f"{name}: {len(b)} places x {b.shape[1]} images, median distance between place centres "
                     f"{_median_centre_distance(xy, b):.0f} m{tau}", fontsize=9)
        pad = 0.03 * span.max()                               # the same map limits in both panels
        ax.set(aspect="equal", xlabel="easting (m)", ylabel="northing (m)",
               xlim=(xy[:, 0].min() - pad, xy[:, 0].max() + pad), ylim=(xy[:, 1].min() - pad, xy[:, 1].max() + pad))
    return axes[0].figure
