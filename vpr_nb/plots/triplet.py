"""The triplet margin loss as a picture: one query's negatives around its margin band, and a batch's triplets.

:func:`plot_triplets` draws Eq. (3) of DW-T-Loss (notebook 02) from the query, positive and negative descriptors
themselves; it calls no random generator, so a notebook's random streams are left as they were.
"""
from __future__ import annotations

import matplotlib.pyplot as plt
import numpy as np
from matplotlib.patches import Circle

from .._checks import as_float_matrix, check_int, check_positive

ACTIVE, SATISFIED = "#d73027", "#1a9850"


def _descriptors(q, p, n):
    qa, pa = as_float_matrix(q, "q").astype(np.float64), as_float_matrix(p, "p").astype(np.float64)
    if pa.shape != qa.shape:
        raise ValueError(f"p must have the shape of q (B, D) = {qa.shape}, got {pa.shape}: one positive per query")
    na = n.detach().cpu().numpy() if hasattr(n, "detach") else np.asarray(n)
    if na.ndim != 3 or na.shape[0] != qa.shape[0] or na.shape[2] != qa.shape[1] or na.shape[1] == 0:
        raise ValueError(f"n must have shape (B, M, D) = ({qa.shape[0]}, M >= 1, {qa.shape[1]}), M negatives per "
                         f"query, got {tuple(na.shape)}")
    na = as_float_matrix(na.reshape(-1, na.shape[2]), "n").astype(np.float64).reshape(na.shape)
    return qa, pa, na


def plot_triplets(q, p, n, margin: float, query: int | None = None, axes=None):
    """Eq. (3), max(0, d(q, p) - d(q, n) + m): which triplets of a batch are active (loss > 0) and which satisfied.

    ``q`` and ``p``: (B, D) query and positive descriptors; ``n``: (B, M, D), M negatives per query; numpy
    arrays or torch tensors. Left: query ``query`` (default: the first with both kinds of negatives) at the
    centre, its positive and negatives at their **true** distances d(q, .), in the directions of the centred
    offsets' first two principal components (directions are only for legibility); the shaded ring from d(q, p)
    to d(q, p) + m is the margin band: a negative inside its outer circle is active. Right: every triplet of the
    batch, d(q, n) against d(q, p), with the line d(q, n) = d(q, p) + m below which a triplet has loss. Two axes
    may be given in ``axes``; returns the figure.
    """
    qa, pa, na = _descriptors(q, p, n)
    margin = check_positive(margin, "margin", allow_zero=True)
    if axes is None:
        _, axes = plt.subplots(1, 2, figsize=(12, 5.4), gridspec_kw={"width_ratios": [1.4, 1]})
    if len(axes) != 2:
        raise ValueError(f"axes must be two matplotlib axes (one query, the batch), got {len(axes)}")
    d_qp = np.linalg.norm(qa - pa, axis=1)                        # (B,)
    d_qn = np.linalg.norm(qa[:, None] - na, axis=2)              # (B, M)
    active = d_qp[:, None] - d_qn + margin > 0                     # loss > 0, Eq. (3)
    mixed = np.flatnonzero(active.any(1) & ~active.all(1))
    b = (int(mixed[0]) if len(mixed) else 0) if query is None else check_int(query, "query", minimum=0,
                                                                              maximum=len(qa) - 1)
    _one_query(axes[0], pa[b] - qa[b], na[b] - qa[b], d_qp[b], d_qn[b], active[b], margin, b)
    _batch(axes[1], d_qp, d_qn, active, margin, b)
    fig = axes[0].figure
    fig.tight_layout()
    return fig


def _one_query(ax, off_p, off_n, d_p, d_n, active, margin, b):
    offsets = np.vstack([off_p[None], off_n])                      # offsets from q: positive, then negatives
    centred = offsets - offsets.mean(0)
    _, _, vt = np.linalg.svd(centred, full_matrices=False)
    xy = centred @ vt[:2].T if len(vt) > 1 else np.c_[centred @ vt[0], np.zeros(len(offsets))]
    angle = np.arctan2(xy[:, 1], xy[:, 0])
    angle = angle - angle[0]                                        # the positive on the +x axis
    radius = np.r_[d_p, d_n]                                       # true distances from q
    pts = radius[:, None] * np.c_[np.cos(angle), np.sin(angle)]
    ax.add_patch(Circle((0, 0), d_p + margin, color="0.85", zorder=0, label=f"margin band, m = {margin:g}"))
    ax.add_patch(Circle((0, 0), d_p, color="white", zorder=0))
    ax.add_patch(Circle((0, 0), d_p, fill=False, ls="--", color="tab:blue", lw=1, label="d(q, p)"))
    ax.plot(*pts[0], "o", color="tab:blue", ms=9, label=f"positive p, d(q, p) = {d_p:.2f}")
    ax.plot([0, pts[0, 0]], [0, pts[0, 1]], color="tab:blue", lw=1)
    for j, ((x, y), a) in enumerate(zip(pts[1:], angle[1:])):
        colour = ACTIVE if active[j] else SATISFIED
        ax.plot([0, x], [0, y], color=colour, lw=0.8, alpha=0.6)
        ax.plot(x, y, "s", color=colour, ms=7)
        ax.annotate(f"n{j + 1}", (x, y), textcoords="offset points", fontsize=8, va="center",
                    xytext=(9 * np.cos(a), 9 * np.sin(a)), ha="left" if np.cos(a) >= 0 else "right")
        ax.text(0.02, 0.8 - 0.055 * j, f"d(q, n{j + 1}) = {d_n[j]:.2f}", color=colour, fontsize=7,
                transform=ax.transAxes)
    ax.text(0.02, 0.96, f"d(q, p) = {d_p:.2f}\nd(q, p) + m = {d_p + margin:.2f}", fontsize=7, va="top",
            transform=ax.transAxes)
    ax.plot(0, 0, "k*", ms=14, label="query q")
    ax.plot([], [], "s", color=ACTIVE, label="negative, active (loss > 0)")
    ax.plot([], [], "s", color=SATISFIED, label="negative, satisfied")
    r = 1.12 * max(radius.max(), d_p + margin)
    ax.set(xlim=(-1.75 * r, r), ylim=(-r, r), aspect="equal", xticks=[], yticks=[],   # the numbers on the left
           title=f"query {b}: true distances from q, PCA directions")
    ax.legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.02), ncol=2, frameon=False)


def _batch(ax, d_qp, d_qn, active, margin, b):
    x = np.repeat(d_qp[:, None], d_qn.shape[1], axis=1)
    lo, hi = min(x.min(), d_qn.min()) - margin, max(x.max(), d_qn.max()) + margin
    line = np.array([lo, hi])
    ax.fill_between(line, line, line + margin, color="0.85", label="margin band: d(q,p) < d(q,n) < d(q,p) + m")
    ax.plot(line, line + margin, color="k", lw=1, label="d(q, n) = d(q, p) + m")
    ax.scatter(x[active], d_qn[active], s=22, color=ACTIVE,
               label=f"active (loss > 0): {int(active.sum())} of {active.size}")
    ax.scatter(x[~active], d_qn[~active], s=22, color=SATISFIED, label=f"satisfied: {int((~active).sum())}")
    ax.scatter(x[b], d_qn[b], s=70, facecolors="none", edgecolors="k", label=f"query {b}'s triplets")
    ax.set(xlim=(lo, hi), ylim=(lo, hi), aspect="equal", xlabel="d(q, p)", ylabel="d(q, n)",
           title="every triplet of the batch, Eq. (3)")
    ax.legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.13), ncol=2, frameon=False)
