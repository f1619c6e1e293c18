"""SALAD's transport plan on one image as a picture: where each position's mass goes, a cluster or the dustbin.

:func:`plot_salad_plan` draws the Sinkhorn plan of Eqs. (2)-(3) of notebook 05 from the plan a SALAD score head
gives one image's feature map; it calls no random generator, so a notebook's random streams are left as they were.
"""
from __future__ import annotations

import matplotlib.pyplot as plt
import numpy as np
from matplotlib.colors import ListedColormap, LogNorm, to_rgba
from matplotlib.patches import Patch

DUSTBIN_COLOUR = "0.15"   # near black: never a cluster colour of tab20


def _cluster_colours(m: int) -> np.ndarray:
    """One RGBA colour per cluster: tab20's for up to 20 clusters, evenly spaced hues beyond."""
    cmap = plt.get_cmap("tab20") if m <= 20 else plt.get_cmap("hsv", m + 1)
    return np.array([cmap(k % cmap.N) for k in range(m)])


def plot_salad_plan(image, plan, grid_shape, dustbin_threshold: float | None = None, axes=None):
    """SALAD's optimal-transport plan with its dustbin row, Eqs. (2)-(3) of notebook 05, on one image.

    ``image``: the image, uint8 (H, W, 3); ``plan``: its transport plan P (not log P), (m + 1, n) with the
    dustbin as the last row, non-negative, every column summing to about 1 (Eq. 3: each position gives mass 1);
    ``grid_shape``: the (h, w) feature map, h * w = n, positions in row-major order (``flatten``); numpy arrays
    or torch tensors. Left: the image with each position coloured by the cluster that receives most of its
    mass, argmax_k P_ki (k < m), and drawn dark when it gives the dustbin more than ``dustbin_threshold`` of
    its mass (default (n - m) / n, the dustbin's share of every position under a uniform plan, since Eq. (3)
    hands the dustbin n - m of the n units). Right: the plan itself, clusters and dustbin row by position, on a
    log colour scale (the dustbin row holds most of the mass), under a strip of the same colours per position.
    Two axes (image, plan) may be given in ``axes``; returns the figure.
    """
    img = np.asarray(image)
    if img.ndim != 3 or img.shape[-1] != 3 or img.dtype != np.uint8:
        raise ValueError(f"image must be one uint8 image of shape (H, W, 3), got {img.dtype} {img.shape}")
    p = plan.detach().cpu().numpy() if hasattr(plan, "detach") else np.asarray(plan)
    if p.dtype == object or not np.issubdtype(p.dtype, np.number) or p.ndim != 2 or p.shape[0] < 2:
        raise ValueError(f"plan must be the (m + 1, n) transport plan, clusters then the dustbin row, got {p.dtype} "
                         f"of shape {tuple(p.shape)}")
    p = p.astype(np.float64)
    if not np.isfinite(p).all() or (p < 0).any():
        raise ValueError("plan must be finite and non-negative: pass exp(log P), not the log plan")
    if not np.allclose(p.sum(0), 1.0, atol=1e-2):
        raise ValueError(f"every column of plan must sum to 1 (Eq. 3: each position gives mass 1), got column sums "
                         f"in [{p.sum(0).min():.3f}, {p.sum(0).max():.3f}]; is the plan transposed or without its dustbin?")
    h, w = (int(s) for s in grid_shape)
    m, n = p.shape[0] - 1, p.shape[1]
    if h * w != n:
        raise ValueError(f"grid_shape {(h, w)} has {h * w} positions but plan has {n} columns")
    if n <= m:
        raise ValueError(f"the dustbin needs more positions than clusters (Eq. 3), got n={n}, m={m}")
    threshold = (n - m) / n if dustbin_threshold is None else float(dustbin_threshold)
    if not 0.0 < threshold < 1.0:
        raise ValueError(f"dustbin_threshold must be a share of a position's mass in (0, 1), got {threshold}")
    if axes is None:
        _, axes = plt.subplots(1, 2, figsize=(13, 4), gridspec_kw={"width_ratios": [1, 1.6]})
    if len(axes) != 2:
        raise ValueError(f"axes must be two matplotlib axes (image, plan), got {len(axes)}")
    colours = _cluster_colours(m)
    main, dustbin_share = p[:m].argmax(0), p[m]
    discarded = dustbin_share > threshold
    rgba = colours[main].copy()
    rgba[discarded] = to_rgba(DUSTBIN_COLOUR)
    ih, iw = img.shape[:2]
    ax = axes[0]
    ax.imshow(img, interpolation="nearest")
    ax.imshow(rgba.reshape(h, w, 4), alpha=0.6, extent=(-0.5, iw - 0.5, ih - 0.5, -0.5), interpolation="nearest")
    for x in np.linspace(-0.5, iw - 0.5, w + 1):       # the feature-map grid, one cell per position
        ax.axvline(x, color="w", lw=0.3, alpha=0.6)
    for y in np.linspace(-0.5, ih - 0.5, h + 1):
        ax.axhline(y, color="w", lw=0.3, alpha=0.6)
    yy, xx = np.divmod(np.flatnonzero(discarded), w)           # a cross on every position the dustbin takes
    ax.scatter((xx + 0.5) * iw / w - 0.5, (yy + 0.5) * ih / h - 0.5, marker="x", s=14, lw=0.8, color="w")
    ax.set(xticks=[], yticks=[], xlim=(-0.5, iw - 0.5), ylim=(ih - 0.5, -0.5),
           title=f"main cluster per position ({len(np.unique(main[~discarded]))} of {m} clusters)")
    ax.legend(handles=[Patch(color=DUSTBIN_COLOUR, alpha=0.6, label=f"x: dustbin share > {threshold:.2f} "
                             f"({discarded.sum()} of {n} positions)")],
              loc="upper center", bbox_to_anchor=(0.5, -0.01), fontsize=8, frameon=False)
    ax = axes[1]
    shown = ax.imshow(np.maximum(p, 1e-6), aspect="auto", cmap="magma", interpolation="nearest",
                      norm=LogNorm(vmin=max(1e-4, float(p[p > 0].min())), vmax=1.0))
    ax.axhline(m - 0.5, color="w", lw=1.2)
    ticks = list(range(0, m, max(1, m // 4))) + [m]
    ax.set_yticks(ticks, [str(k) for k in ticks[:-1]] + ["dustbin"])
    ax.set(xlabel="position i (row by row over the image)", ylabel="cluster k",
           title=f"plan P: columns sum to 1, cluster rows to 1, the dustbin row to n - m = {n - m}")
    strip = ax.inset_axes([0.0, 1.0, 1.0, 0.06], sharex=ax)   # the left panel's colour of every position
    strip.imshow(np.arange(n)[None], cmap=ListedColormap(rgba), aspect="auto", interpolation="nearest", vmin=0,
                 vmax=n - 1)
    strip.set_axis_off()
    ax.title.set_y(1.08)
    ax.figure.colorbar(shown, ax=ax, fraction=0.03, pad=0.01).set_label("P_ki (log scale)", fontsize=8)
    return ax.figure
