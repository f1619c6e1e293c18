"""The GDS profile as a picture: descriptor distance against geographic distance, and how two bins mis-order.

:func:`plot_gds_misordering` draws Eqs. (1) and (3) of notebook 06 from a :class:`vpr_nb.gds.GDSProfile`; it calls
no random generator, so a notebook's random streams are left as they were.
"""
from __future__ import annotations

import math

import matplotlib.pyplot as plt
import numpy as np

from ..gds import GDSProfile, misordering_probability

NEAR, FAR = "tab:blue", "tab:red"   # the bins of d1 (the nearer pairs) and d2 (the farther ones)


def _normal_pdf(x: np.ndarray, mu: float, sd: float) -> np.ndarray:
    return np.exp(-0.5 * ((x - mu) / sd) ** 2) / (sd * math.sqrt(2.0 * math.pi))


def plot_gds_misordering(profile, d1: float, d2: float, axes=None, label: str | None = None):
    """A GDS profile, Eq. (1) of notebook 06, and its mis-ordering probability p(d1, d2), Eq. (3).

    ``profile``: a :class:`vpr_nb.gds.GDSProfile` (from :func:`vpr_nb.gds.gds_profile`); ``d1 < d2``: two
    geographic distances in metres, each in a non-empty bin of the profile; ``label`` names the descriptor in
    the titles. Left: the mean descriptor distance mu_b of every bin against its centre, with the band
    mu_b +- sigma_b, and the bins of d1 and d2 marked. Right: the Gaussians N(mu_1, sigma_1^2) and
    N(mu_2, sigma_2^2) of Eq. (3) for the two bins (with the histograms of their pairs when the profile kept
    them, ``keep_pairs=True``), their overlap shaded, and p(d1, d2) = Phi((mu_1 - mu_2) / sqrt(sigma_1^2 +
    sigma_2^2)) = P(D(d2) < D(d1)) from :func:`vpr_nb.gds.misordering_probability`: the more the two overlap,
    the likelier the farther image is ranked first. Two axes may be given in ``axes``; returns the figure.
    """
    if not isinstance(profile, GDSProfile):
        raise ValueError(f"profile must be a GDSProfile from vpr_nb.gds.gds_profile(), got {type(profile).__name__}")
    for name, d in (("d1", d1), ("d2", d2)):
        if isinstance(d, bool) or not isinstance(d, (int, float, np.integer, np.floating)) or not math.isfinite(d):
            raise ValueError(f"{name} must be a finite distance in metres, got {d!r}")
    if not d1 < d2:
        raise ValueError(f"d1 must be smaller than d2 (d1 is the nearer pair), got d1={d1}, d2={d2}")
    p = misordering_probability(profile, float(d1), float(d2))   # checks both bins: in range, non-empty
    nb = len(profile.count)
    b1, b2 = (min(int(math.floor(d / profile.bin_width)), nb - 1) for d in (d1, d2))
    if axes is None:
        _, axes = plt.subplots(1, 2, figsize=(12, 3.8), gridspec_kw={"width_ratios": [1.3, 1]})
    if len(axes) != 2:
        raise ValueError(f"axes must be two matplotlib axes (profile, bins), got {len(axes)}")
    c, mu, sd = profile.bin_centers, profile.mean, profile.std
    name = f"{label}: " if label else ""
    ax = axes[0]
    ax.fill_between(c, mu - sd, mu + sd, color="0.6", alpha=0.3, lw=0, label="mean ± 1 std (band)")
    ax.plot(c, mu, color="0.2", marker="o", ms=3, lw=1.5, label="mean descriptor distance")
    for b, d, colour, which in ((b1, d1, NEAR, "d_1"), (b2, d2, FAR, "d_2")):
        ax.errorbar(c[b], mu[b], yerr=sd[b], color=colour, marker="o", ms=7, capsize=4, lw=2, zorder=3,
                    label=f"${which}$ = {d:g} m: bin [{profile.bin_edges[b]:.1f}, {profile.bin_edges[b + 1]:.1f}) m")
    ax.set(xlabel="geographic distance (m), bin centres", ylabel="descriptor distance (L2)",
           title=f"{name}GDS profile, Eq. (1)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, loc="lower right")
    ax = axes[1]
    lo = min(mu[b1] - 4 * sd[b1], mu[b2] - 4 * sd[b2])
    hi = max(mu[b1] + 4 * sd[b1], mu[b2] + 4 * sd[b2])
    x = np.linspace(lo, hi, 400)
    pdf1 = _normal_pdf(x, mu[b1], max(sd[b1], 1e-12))
    pdf2 = _normal_pdf(x, mu[b2], max(sd[b2], 1e-12))
    if profile.pair_desc is not None:                        # the pairs themselves, sorted bin after bin
        start = np.concatenate([[0], np.cumsum(profile.count)])
        for b, colour in ((b1, NEAR), (b2, FAR)):
            ax.hist(profile.pair_desc[start[b]:start[b + 1]], bins=30, range=(lo, hi), density=True,
                    histtype="step", color=colour, alpha=0.6)
    ax.fill_between(x, np.minimum(pdf1, pdf2), color="tab:purple", alpha=0.35, lw=0, label="overlap")
    ax.plot(x, pdf1, color=NEAR, lw=2, label=f"$D(d_1)$, {d1:g} m: N({mu[b1]:.3f}, {sd[b1]:.3f}²)")
    ax.plot(x, pdf2, color=FAR, lw=2, label=f"$D(d_2)$, {d2:g} m: N({mu[b2]:.3f}, {sd[b2]:.3f}²)")
    ax.set(xlabel="descriptor distance (L2)", ylabel="density", ylim=(0, None),
           title=f"{name}$p(d_1, d_2) = P(D(d_2) < D(d_1))$ = {p:.3f}, Eq. (3)")
    ax.legend(fontsize=7, loc="upper right")
    fig = axes[0].figure
    fig.tight_layout()
    return fig
