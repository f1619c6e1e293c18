"""The placebo of DW-T-Loss: Eq. (9) with the batch's query-positive distances shuffled across its queries.

DW-T-Loss (Xiong, Xu, Meng) weights each query's triplets by Eq. (4), ``w(geo_qp)``, the weight of its own
query-positive distance. If it beats T-Loss, two things changed at once: the triplets are *ranked* (a near
positive weighs more than a far one) and the loss is *rescaled and made uneven* (weights between ``w(radius)``
and ``1 / eps`` instead of 1). :class:`PlaceboDWTripletLoss`    keeps the second and removes the first: every
batch gets exactly the weights DW-T-Loss would give it (same values, same distribution, same sum), but each
query gets the weight of another query's distance, drawn by a seeded random permutation, so a weight says
nothing about its own triplet. DW-T-Loss beating its placebo is evidence for the ranking; a placebo that does
as well says the gain is the scale or the noise.

===============================  =====================================================================
:func:`placebo_permutation`      the batch's permutation, seeded by ``seed`` and the distances' values
:func:`placebo_dw_triplet_loss`  Eq. (9) with ``geo_qp[permutation]`` in place of ``geo_qp``
:class:`PlaceboDWTripletLoss`    the loss object, usable wherever :class:`DWTripletLoss` is
===============================  =====================================================================
"""
from __future__ import annotations

import hashlib
from dataclasses import dataclass

import numpy as np
import torch

from .._checks import check_int, check_positive
from ._common import _geo_like
from .triplet import DEFAULT_EPS, DEFAULT_SIGMA, TripletFamilyLoss, _check_geo_given, dw_triplet_loss


def _geo_values(geo_qp) -> np.ndarray:
    """``geo_qp`` as a 1-D float64 numpy array (a tensor is read as the values it holds, on any device)."""
    if isinstance(geo_qp, torch.Tensor):
        geo_qp = geo_qp.detach().cpu().double().numpy()
    try:
        geo = np.asarray(geo_qp, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"geo_qp must be a (B,) array of distances in metres, got {type(geo_qp).__name__}") from None
    if geo.ndim != 1 or len(geo) == 0:
        raise ValueError(f"geo_qp must be a non-empty (B,) array of distances in metres, got shape {geo.shape}")
    return geo


def placebo_permutation(geo_qp, seed: int = 0) -> np.ndarray:
    """The placebo's permutation of a batch: ``(B,)`` int64, a uniformly random permutation of ``range(B)``.

    Seeded by ``seed`` and the bytes of the distances (as float64): the same batch gets the same permutation
    (so a loss evaluated twice on one batch, as :class:`vpr_nb.training.TripletSource` does for its collapsed
    loss, agrees with itself), another batch an independent one, and the object holds no state.
    """
    seed = check_int(seed, "seed", minimum=0)
    geo = _geo_values(geo_qp)
    key = int.from_bytes(hashlib.blake2b(np.ascontiguousarray(geo, dtype="<f8").tobytes(), digest_size=8).digest(),
                         "little")
    return np.random.default_rng([seed, key]).permutation(len(geo))


def placebo_dw_triplet_loss(q: torch.Tensor, p: torch.Tensor, n: torch.Tensor, geo_qp, permutation,
                            sigma: float = DEFAULT_SIGMA, eps: float = DEFAULT_EPS,
                            reduction: str = "sum") -> torch.Tensor:
    """Eq. (9) of DW-T-Loss with query ``i`` weighted by ``w(geo_qp[permutation[i]])`` (Eq. (4)).

    ``permutation`` must be a permutation of ``range(B)``; the identity gives :func:`dw_triplet_loss`.
    """
    geo = _geo_like(geo_qp, q)
    perm = np.asarray(permutation)
    b = geo.shape[0]
    if perm.shape != (b,) or not np.issubdtype(perm.dtype, np.integer) or \
            not np.array_equal(np.sort(perm), np.arange(b)):
        raise ValueError(f"permutation must be a permutation of range({b}) (one index per query), got {perm!r}")
    return dw_triplet_loss(q, p, n, geo[torch.as_tensor(perm, device=geo.device)], sigma, eps, reduction)


@dataclass(frozen=True)
class PlaceboDWTripletLoss(TripletFamilyLoss):
    """Placebo DW-T-Loss: Eq. (9) with the batch's query-positive distances randomly permuted across its
    queries (:func:`placebo_dw_triplet_loss` with :func:`placebo_permutation`; ``sigma`` > 0, ``eps`` > 0,
    ``seed`` >= 0). Same interface as :class:`DWTripletLoss`.

    Controls for everything DW-T-Loss changes except the ranking: each batch's weights have DW-T-Loss's
    values (their distribution, mean and sum), but a query's weight no longer depends on its own positive's
    distance, hence on how useful its triplet is.
    """

    sigma: float = DEFAULT_SIGMA
    eps: float = DEFAULT_EPS
    seed: int = 0

    def __post_init__(self):
        object.__setattr__(self, "sigma", check_positive(self.sigma, "sigma"))
        object.__setattr__(self, "eps", check_positive(self.eps, "eps"))
        object.__setattr__(self, "seed", check_int(self.seed, "seed", minimum=0))

    def permutation(self, geo_qp) -> np.ndarray:
        """The permutation this loss applies to a batch with these distances (:func:`placebo_permutation`)."""
        return placebo_permutation(geo_qp, self.seed)

    def __call__(self, q, p, n, geo_qp=None):
        _check_geo_given(self, geo_qp)
        return placebo_dw_triplet_loss(q, p, n, geo_qp, self.permutation(geo_qp), self.sigma, self.eps)
