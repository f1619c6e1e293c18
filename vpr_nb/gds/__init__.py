"""Geographic Distance Sensitivity (GDS) of a VPR embedding.

CliqueMining (Izquierdo & Civera, ECCV 2024) argues that a VPR descriptor should keep sorting
images correctly *at small geographic distances*: among the top-k retrievals of a query, the
image taken 5 m away should be closer in descriptor space than the one taken 20 m away. The
paper plots, for image pairs binned by their geographic distance, the descriptor distance
(mean and spread, its Fig. 1). No public code for that analysis exists, so this package defines
it precisely, one idea per module (each module's docstring holds the full definition):

=================================  ======================================================================
:mod:`~vpr_nb.gds.pairs`           the pair set (``query-db`` or ``all`` pairs with geographic distance
                                   ``<= max_distance``, by k-d tree range search) and the two distances of a
                                   pair: geographic ``||utm_a - utm_b||_2`` (m) and descriptor ``||a - b||_2``,
                                   ``sqrt(max(|a|^2 + |b|^2 - 2 a.b, 0))`` from Gram matrices
:mod:`~vpr_nb.gds.binning`         the bins ``[b*w, (b+1)*w)`` (the last one closed) and, per bin, the count,
                                   mean, population std (ddof = 0) and quantiles (numpy's ``"linear"``) of the
                                   descriptor distance, in bounded memory
:mod:`~vpr_nb.gds.profile`         :func:`gds_profile` -> :class:`GDSProfile`: the per-bin statistics, the
                                   ``mean +- 1 std`` band and the slope of the weighted least-squares line
                                   ``mean_b ~ intercept + slope * center_b`` (weights ``count_b``)
:mod:`~vpr_nb.gds.misordering`     :func:`misordering_probability` and :func:`misordering_matrix`:
                                   ``P(D(d2) < D(d1))`` for ``d1 < d2``, ``"gaussian"``
                                   ``Phi((mu1 - mu2) / sqrt(sigma1^2 + sigma2^2))`` or ``"empirical"``
:mod:`~vpr_nb.gds.topk`            :func:`topk_order_agreement` and :func:`query_topk`: are the top-k
                                   retrievals of a query sorted by geographic distance (fraction of correctly
                                   ordered pairs, Kendall tau-b)
=================================  ======================================================================
"""
from __future__ import annotations

from .misordering import misordering_matrix, misordering_probability
from .profile import MAX_BINS, GDSProfile, gds_profile
from .topk import OrderAgreement, QueryTopK, query_topk, topk_order_agreement

__all__ = ["gds_profile", "GDSProfile", "MAX_BINS", "misordering_probability", "misordering_matrix",
           "topk_order_agreement", "OrderAgreement", "query_topk", "QueryTopK"]
