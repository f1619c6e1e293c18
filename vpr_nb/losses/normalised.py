"""DW-T-Loss with its weight divided by its batch mean: Eq. (9)'s ranking without Eq. (4)'s scale.

Eq. (4)'s weight ``w = (1 + eps) / (geo_qp / sigma + eps) - 1`` is about 9 for every positive within 10 m at
the paper's sigma = 800 m, so under SGD DW-T-Loss steps about 9 times as far as CE-Loss (Eqs. 5-8) at one lr.
Dividing each batch's weights by their mean keeps their ranking (a near positive still weighs more than a far
one) and sets their mean to 1, CE-Loss's constant weight:

    L = sum_i (w_i / mean_j w_j) * -log d_hat_n,i        (Eq. 9 with w_i / mean_j w_j for w_i)

At sigma = 800 m (weights equal to 2 %) this is CE-Loss to within 2 %: if plain DW-T-Loss then beats CE-Loss under
SGD and this loss does not, the gain was the step size. The mean is taken over the batch's queries (one weight
per query, as Eq. 9) and is treated as a constant of the batch only through its value: it is computed from the
distances, which carry no gradient.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F

from ._common import _check_reduction, _geo_like, _reduce, _triplet_distances
from .triplet import DEFAULT_EPS, DEFAULT_SIGMA, DWTripletLoss, _check_geo_given, distance_weight


def batch_mean_dw_triplet_loss(q: torch.Tensor, p: torch.Tensor, n: torch.Tensor, geo_qp,
                               sigma: float = DEFAULT_SIGMA, eps: float = DEFAULT_EPS,
                               reduction: str = "sum") -> torch.Tensor:
    """Eq. (9) with each query's Eq. (4) weight divided by the batch's mean weight.

    Refuses a batch whose mean weight is not positive (positives beyond ``sigma`` weigh < 0): the division
    would flip or blow up every triplet's sign; keep ``sigma`` above the positive radius.
    """
    _check_reduction(reduction)
    d_qp, d_qn, single = _triplet_distances(q, p, n)
    w = distance_weight(_geo_like(geo_qp, q), sigma, eps)
    mean = w.mean()
    if not bool(mean > 0):
        raise ValueError(f"the batch's mean Eq. (4) weight is {float(mean):.3g}, not positive: its positives lie "
                         f"near or beyond sigma = {sigma:g} m; use a sigma larger than the positive radius")
    return _reduce((w / mean).unsqueeze(1) * F.softplus(d_qp - d_qn), single, reduction)


@dataclass(frozen=True)
class BatchMeanDWTripletLoss(DWTripletLoss):
    """DW-T-Loss with its weight divided by its batch mean (:func:`batch_mean_dw_triplet_loss`): the parameters
    (``sigma`` > 0, ``eps`` > 0) and interface of :class:`vpr_nb.losses.DWTripletLoss`."""

    def __call__(self, q, p, n, geo_qp=None):
        _check_geo_given(self, geo_qp)
        return batch_mean_dw_triplet_loss(q, p, n, geo_qp, self.sigma, self.eps)
