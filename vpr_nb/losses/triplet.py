"""The triplet family of DW-T-Loss, Eqs. (3)-(9), as loss functions and as loss objects holding their parameters.

Triplet family, from "Distance-Ranking-Based Weighted Triplet Loss for Visual Place
Recognition" (Xiong, Xu, Meng):

==============================  ==============  ====================================================
function                        paper equation  formula, per triplet (q, p, n)
==============================  ==============  ====================================================
:func:`triplet_loss`            Eq. (3)         ``max(0, d(q,p) - d(q,n) + m)``
:func:`distance_weight`         Eq. (4)         ``w = (1 + eps) / (geo_qp / sigma + eps) - 1``
:func:`weighted_triplet_loss`   Eq. (4) x (3)   ``w * max(0, d(q,p) - d(q,n) + m)`` (W-T-Loss)
:func:`ce_triplet_loss`         Eqs. (5)-(8)    ``-log d_hat_n = softplus(d(q,p) - d(q,n))``
:func:`dw_triplet_loss`         Eq. (9)         ``-w * log d_hat_n`` (DW-T-Loss)
==============================  ==============  ====================================================

Conventions of the triplet family:

- ``q``, ``p`` are ``(B, D)`` descriptors; ``n`` is ``(B, D)`` (one negative per query) or
  ``(B, M, D)`` (M negatives per query, each forming one triplet with the query's positive).
- ``d(a, b)`` is the plain (not squared) Euclidean distance, without the ``eps=1e-6`` that
  :class:`torch.nn.TripletMarginLoss` adds inside its distance; both agree to ~``sqrt(D)*1e-6``.
- The default reduction is the paper's ``"sum"`` over all triplets; ``"mean"`` averages over the
  ``B*M`` triplets and ``"none"`` returns the ``(B, M)`` (or ``(B,)`` for a 2-D ``n``) losses.
- Margins differ between code bases: the original NetVLAD MATLAB code uses ``m = 0.1`` on
  *squared* L2 distances, whereas Nanne's pytorch-NetVlad uses ``m = sqrt(0.1)`` on plain L2
  (``TripletMarginLoss(margin=0.1**0.5, p=2)``). The default here is the paper's ``m = 0.1``.

Loss objects: :class:`TripletFamilyLoss` and its subclasses :class:`TripletLoss`, :class:`WeightedTripletLoss`,
:class:`CETripletLoss` and :class:`DWTripletLoss` hold their parameters, validated when they are built, and
call the function above with them (the same floating-point operations).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from .._checks import check_positive
from ._common import _check_reduction, _geo_like, _reduce, _triplet_distances

# Every default of the triplet family, in one place (the functions' and the loss classes' signatures use them).
DEFAULT_MARGIN = 0.1           # Eq. (3) margin m, on plain L2 distances (the paper's value)
DEFAULT_SIGMA = 800.0          # Eq. (4) sigma, metres: the weight is 0 at this query-positive distance
DEFAULT_EPS = 0.1              # Eq. (4) eps: the weight at 0 m is 1 / eps


def triplet_loss(q: torch.Tensor, p: torch.Tensor, n: torch.Tensor, margin: float = DEFAULT_MARGIN,
                 reduction: str = "sum") -> torch.Tensor:
    """Triplet margin loss, Eq. (3) of DW-T-Loss: ``sum max(0, d(q,p) - d(q,n) + margin)``.

    Equals ``torch.nn.TripletMarginLoss(margin, p=2, reduction="sum")`` up to the ``eps=1e-6``
    torch adds inside its distance. ``n`` may be ``(B, D)`` or ``(B, M, D)``.
    """
    _check_reduction(reduction)
    margin = check_positive(margin, "margin", allow_zero=True)
    d_qp, d_qn, single = _triplet_distances(q, p, n)
    return _reduce(F.relu(d_qp - d_qn + margin), single, reduction)


def distance_weight(geo_qp, sigma: float = DEFAULT_SIGMA, eps: float = DEFAULT_EPS):
    """Geographic weight of a query-positive pair, Eq. (4) of DW-T-Loss.

    ``w = (1 + eps) / (geo_qp / sigma + eps) - 1`` decreases with distance: ``w = 1 / eps`` at 0 m
    (10 for the default ``eps = 0.1``, so ``eps`` sets the largest weight), ``w = 0`` at
    ``geo_qp = sigma`` and **negative beyond sigma**, down to ``-1`` far away. Not clipped: a
    "positive" farther than sigma then *rewards* a violated triplet, which is why sigma must
    exceed the positive radius.

    Elementwise on any shape. A torch tensor gives a tensor (integer tensors become the default
    float dtype); anything else (numpy array, list, scalar) gives a float64 numpy array.
    """
    sigma = check_positive(sigma, "sigma")
    eps = check_positive(eps, "eps")
    if isinstance(geo_qp, torch.Tensor):
        geo = geo_qp if geo_qp.is_floating_point() else geo_qp.to(torch.get_default_dtype())
        finite, nonneg = bool(torch.isfinite(geo).all()), bool((geo >= 0).all())
    else:
        try:
            geo = np.asarray(geo_qp, dtype=np.float64)
        except (TypeError, ValueError):
            raise ValueError(f"geo_qp must be numbers (metres), got {type(geo_qp).__name__}") from None
        finite, nonneg = bool(np.isfinite(geo).all()), bool((geo >= 0).all())
    if not finite:
        raise ValueError("geo_qp contains NaN or inf; every query-positive pair needs a valid distance in metres")
    if not nonneg:
        raise ValueError("geo_qp contains negative distances; geographic distances are >= 0 metres")
    return (1.0 + eps) / (geo / sigma + eps) - 1.0


def weighted_triplet_loss(q: torch.Tensor, p: torch.Tensor, n: torch.Tensor, geo_qp,
                          margin: float = DEFAULT_MARGIN, sigma: float = DEFAULT_SIGMA, eps: float = DEFAULT_EPS,
                          reduction: str = "sum") -> torch.Tensor:
    """W-T-Loss: Eq. (4) weight times Eq. (3) hinge, ``sum w(geo_qp) * max(0, d(q,p) - d(q,n) + margin)``.

    Each query's weight (from its ``(B,)`` query-positive distance in metres) multiplies all M of
    its triplets. Weights are negative for ``geo_qp > sigma`` (see :func:`distance_weight`).
    """
    _check_reduction(reduction)
    margin = check_positive(margin, "margin", allow_zero=True)
    d_qp, d_qn, single = _triplet_distances(q, p, n)
    w = distance_weight(_geo_like(geo_qp, q), sigma, eps)
    return _reduce(w.unsqueeze(1) * F.relu(d_qp - d_qn + margin), single, reduction)


def ce_triplet_loss(q: torch.Tensor, p: torch.Tensor, n: torch.Tensor, reduction: str = "sum") -> torch.Tensor:
    """Cross-entropy triplet loss, Eqs. (5)-(8) of DW-T-Loss: ``sum -log d_hat_n``.

    ``d_hat_n = e^{d(q,n)} / (e^{d(q,p)} + e^{d(q,n)})`` (softmax of the two distances), so
    ``-log d_hat_n = softplus(d(q,p) - d(q,n))``, which stays finite for any distance.
    """
    _check_reduction(reduction)
    d_qp, d_qn, single = _triplet_distances(q, p, n)
    return _reduce(F.softplus(d_qp - d_qn), single, reduction)


def dw_triplet_loss(q: torch.Tensor, p: torch.Tensor, n: torch.Tensor, geo_qp, sigma: float = DEFAULT_SIGMA,
                    eps: float = DEFAULT_EPS, reduction: str = "sum") -> torch.Tensor:
    """DW-T-Loss, Eq. (9): ``sum -w(geo_qp) * log d_hat_n`` (Eq. (4) weight times Eqs. (5)-(8)).

    Weights are negative for ``geo_qp > sigma`` (see :func:`distance_weight`).
    """
    _check_reduction(reduction)
    d_qp, d_qn, single = _triplet_distances(q, p, n)
    w = distance_weight(_geo_like(geo_qp, q), sigma, eps)
    return _reduce(w.unsqueeze(1) * F.softplus(d_qp - d_qn), single, reduction)


# ----------------------------------------------------------------------------------------------
# loss objects: the parameters of a loss held and validated in one place, for the batch sources
# ----------------------------------------------------------------------------------------------
class TripletFamilyLoss:
    """A loss of DW-T-Loss's triplet family, called as ``loss(q, p, n, geo_qp)`` -> the summed loss.

    ``q``, ``p`` are ``(B, D)``, ``n`` is ``(B, D)`` or ``(B, M, D)`` and ``geo_qp`` the ``(B,)``
    query-positive distances in metres (read only by the distance-weighted losses, Eq. (4)). The
    reduction is the paper's sum over all triplets; :class:`vpr_nb.training.TripletSource` divides it by
    the number of queries. Subclasses: :class:`TripletLoss`, :class:`WeightedTripletLoss`,
    :class:`CETripletLoss`, :class:`DWTripletLoss`.
    """

    def __call__(self, q: torch.Tensor, p: torch.Tensor, n: torch.Tensor, geo_qp=None) -> torch.Tensor:
        raise NotImplementedError


def _check_geo_given(loss, geo_qp) -> None:
    if geo_qp is None:
        raise ValueError(f"{type(loss).__name__} weights each query by Eq. (4) and needs geo_qp, the (B,) "
                         f"query-positive distances in metres: call loss(q, p, n, geo_qp)")


@dataclass(frozen=True)
class TripletLoss(TripletFamilyLoss):
    """T-Loss, Eq. (3) of DW-T-Loss: ``sum max(0, d(q,p) - d(q,n) + margin)`` (see :func:`triplet_loss`).

    ``margin`` >= 0, on plain (not squared) L2 distances. ``geo_qp`` is accepted and not used.
    """

    margin: float = DEFAULT_MARGIN

    def __post_init__(self):
        object.__setattr__(self, "margin", check_positive(self.margin, "margin", allow_zero=True))

    def __call__(self, q, p, n, geo_qp=None):
        return triplet_loss(q, p, n, self.margin)


@dataclass(frozen=True)
class WeightedTripletLoss(TripletFamilyLoss):
    """W-T-Loss, Eq. (4) x Eq. (3): ``sum w(geo_qp) * max(0, d(q,p) - d(q,n) + margin)``
    (see :func:`weighted_triplet_loss`; ``w`` is :func:`distance_weight` with ``sigma`` > 0, ``eps`` > 0)."""

    margin: float = DEFAULT_MARGIN
    sigma: float = DEFAULT_SIGMA
    eps: float = DEFAULT_EPS

    def __post_init__(self):
        object.__setattr__(self, "margin", check_positive(self.margin, "margin", allow_zero=True))
        object.__setattr__(self, "sigma", check_positive(self.sigma, "sigma"))
        object.__setattr__(self, "eps", check_positive(self.eps, "eps"))

    def __call__(self, q, p, n, geo_qp=None):
        _check_geo_given(self, geo_qp)
        return weighted_triplet_loss(q, p, n, geo_qp, self.margin, self.sigma, self.eps)


@dataclass(frozen=True)
class CETripletLoss(TripletFamilyLoss):
    """CE-Loss, Eqs. (5)-(8) of DW-T-Loss: ``sum -log d_hat_n = sum softplus(d(q,p) - d(q,n))``
    (see :func:`ce_triplet_loss`). No parameters; ``geo_qp`` is accepted and not used."""

    def __call__(self, q, p, n, geo_qp=None):
        return ce_triplet_loss(q, p, n)


@dataclass(frozen=True)
class DWTripletLoss(TripletFamilyLoss):
    """DW-T-Loss, Eq. (9): ``sum -w(geo_qp) * log d_hat_n``, the Eq. (4) weight times Eqs. (5)-(8)
    (see :func:`dw_triplet_loss`; ``sigma`` > 0, ``eps`` > 0)."""

    sigma: float = DEFAULT_SIGMA
    eps: float = DEFAULT_EPS

    def __post_init__(self):
        object.__setattr__(self, "sigma", check_positive(self.sigma, "sigma"))
        object.__setattr__(self, "eps", check_positive(self.eps, "eps"))

    def __call__(self, q, p, n, geo_qp=None):
        _check_geo_given(self, geo_qp)
        return dw_triplet_loss(q, p, n, geo_qp, self.sigma, self.eps)
