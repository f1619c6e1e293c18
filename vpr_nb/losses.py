"""Training losses for VPR: the triplet family of DW-T-Loss and Multi-Similarity.

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

Multi-Similarity (Wang et al., CVPR 2019), as used to train SALAD and CliqueMining through
pytorch-metric-learning: :func:`multi_similarity_loss` and :func:`multi_similarity_miner`.

Local InfoNCE (the dense form of van den Oord et al.'s InfoNCE, as in DenseCL, Wang et al., CVPR 2021), a
term of the course backbone's pretraining (:mod:`vpr_nb.pretrain`): :func:`local_infonce`.

Loss objects, for the batch sources of :mod:`vpr_nb.training`: each holds its parameters, validated when
it is built, and calls the function above with them (the same floating-point operations):

==============================  ==============  ============================================  ===============
object                          paper equation  parameters                                    source
==============================  ==============  ============================================  ===============
:class:`TripletLoss`            Eq. (3)         ``margin``                                    TripletSource
:class:`WeightedTripletLoss`    Eq. (4) x (3)   ``margin``, ``sigma``, ``eps``                TripletSource
:class:`CETripletLoss`          Eqs. (5)-(8)    (none)                                        TripletSource
:class:`DWTripletLoss`          Eq. (9)         ``sigma``, ``eps``                            TripletSource
:class:`MultiSimilarityLoss`    Wang Eq. (6)    ``alpha``, ``beta``, ``base``, ``miner_epsilon``  PlaceBatchSource
==============================  ==============  ============================================  ===============

Every default value lives once, in the ``DEFAULT_*`` constants below, which both the functions and the
classes use.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np
import torch
import torch.nn.functional as F

from vpr_nb._checks import check_positive, check_tensor

__all__ = [
    "triplet_loss",
    "distance_weight",
    "weighted_triplet_loss",
    "ce_triplet_loss",
    "dw_triplet_loss",
    "multi_similarity_loss",
    "multi_similarity_miner",
    "local_infonce",
    "LOCAL_NEGATIVES",
    "TripletFamilyLoss",
    "TripletLoss",
    "WeightedTripletLoss",
    "CETripletLoss",
    "DWTripletLoss",
    "MultiSimilarityLoss",
    "LOSSES",
    "TRIPLET_LOSSES",
]

# Every default of this module, in one place (the functions' and the loss classes' signatures use them).
DEFAULT_MARGIN = 0.1           # Eq. (3) margin m, on plain L2 distances (the paper's value)
DEFAULT_SIGMA = 800.0          # Eq. (4) sigma, metres: the weight is 0 at this query-positive distance
DEFAULT_EPS = 0.1              # Eq. (4) eps: the weight at 0 m is 1 / eps
DEFAULT_MS_ALPHA = 1.0         # Multi-Similarity alpha (positive pairs), Wang et al. Eq. (6)
DEFAULT_MS_BETA = 50.0         # Multi-Similarity beta (negative pairs)
DEFAULT_MS_BASE = 0.0          # Multi-Similarity threshold lambda
DEFAULT_MS_MINER_EPSILON = 0.1 # Multi-Similarity miner margin epsilon (Sec. 3.3); None in a loss: no mining

_REDUCTIONS = ("sum", "mean", "none")
LOCAL_NEGATIVES = ("image", "batch")   # local_infonce: a position's negatives come from its image / the batch

MinerPairs = tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]


# ----------------------------------------------------------------------------------------------
# private helpers
# ----------------------------------------------------------------------------------------------
def _check_reduction(reduction: str) -> None:
    if reduction not in _REDUCTIONS:
        raise ValueError(f"reduction must be one of {_REDUCTIONS} ('sum' is the paper's), got {reduction!r}")


def _triplet_distances(q: torch.Tensor, p: torch.Tensor, n: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, bool]:
    """Validate a batch of triplets and return ``d(q,p)`` ``(B, 1)``, ``d(q,n)`` ``(B, M)``, 2-D-``n`` flag.

    The single place where the triplet family measures plain Euclidean distances. NaN/inf are
    looked for in the ``B*(M+1)`` distances rather than in the ``B*(M+2)*D`` inputs (every input
    value reaches a distance, so a non-finite one makes that distance non-finite); only then are
    the inputs searched, to name the culprit. This keeps validation cheap next to the loss itself.
    """
    check_tensor(q, "q", ndim=2, finite=False)
    check_tensor(p, "p", ndim=2, finite=False)
    check_tensor(n, "n", ndim=(2, 3), finite=False)
    if q.shape[0] == 0 or q.shape[1] == 0:
        raise ValueError(f"q must be a non-empty (B, D) batch of descriptors, got shape {tuple(q.shape)}")
    if p.shape != q.shape:
        raise ValueError(f"p must have the same (B, D) shape as q {tuple(q.shape)}: one positive per query; "
                         f"got {tuple(p.shape)}")
    single = n.ndim == 2
    negatives = n.unsqueeze(1) if single else n
    if negatives.shape[0] != q.shape[0] or negatives.shape[2] != q.shape[1]:
        raise ValueError(f"n must be (B, D) or (B, M, D) with B={q.shape[0]} and D={q.shape[1]} as in q, "
                         f"got {tuple(n.shape)}")
    if negatives.shape[1] == 0:
        raise ValueError("n has zero negatives per query (M=0); every query needs at least one negative")
    for name, t in (("p", p), ("n", n)):
        if t.dtype != q.dtype or t.device != q.device:
            raise ValueError(f"{name} is {t.dtype} on {t.device} but q is {q.dtype} on {q.device}; "
                             f"convert with {name}.to(q)")
    d_qp = torch.linalg.vector_norm(q - p, dim=1, keepdim=True)
    d_qn = torch.linalg.vector_norm(q.unsqueeze(1) - negatives, dim=2)
    if not bool(torch.isfinite(d_qp).all() & torch.isfinite(d_qn).all()):
        for name, t in (("q", q), ("p", p), ("n", n)):
            check_tensor(t, name)  # raises, naming the input that holds NaN or inf
        raise ValueError(f"descriptor distances overflow {q.dtype}: the values are finite but too large "
                         f"(max |x| = {max(t.abs().max().item() for t in (q, p, n)):.3g}); L2-normalise the descriptors")
    return d_qp, d_qn, single


def _reduce(losses: torch.Tensor, single: bool, reduction: str) -> torch.Tensor:
    """Reduce ``(B, M)`` per-triplet losses: ``sum``, ``mean`` over B*M, or ``none`` ((B,) if ``single``)."""
    if reduction == "sum":
        return losses.sum()
    if reduction == "mean":
        return losses.mean()
    return losses.squeeze(1) if single else losses


def _geo_like(geo_qp, q: torch.Tensor) -> torch.Tensor:
    """``geo_qp`` as a ``(B,)`` tensor with the dtype and device of ``q`` (values checked by distance_weight)."""
    try:
        geo = geo_qp if isinstance(geo_qp, torch.Tensor) else torch.as_tensor(np.asarray(geo_qp))
    except (TypeError, ValueError, RuntimeError) as exc:
        raise ValueError(f"geo_qp must be a (B,) array of distances in metres; could not convert: {exc}") from None
    if geo.dtype == torch.bool or geo.is_complex():
        raise ValueError(f"geo_qp must hold real numbers (metres), got dtype {geo.dtype}")
    if geo.shape != (q.shape[0],):
        raise ValueError(f"geo_qp must have shape (B,) = ({q.shape[0]},): the query-positive distance of each "
                         f"query, got {tuple(geo.shape)}")
    return geo.to(device=q.device, dtype=q.dtype)


def _check_labels(labels, batch: int, device: torch.device) -> torch.Tensor:
    """Return ``labels`` as a 1-D tensor of length ``batch`` on ``device`` (place ids, no NaN)."""
    try:
        labels = torch.as_tensor(labels if isinstance(labels, torch.Tensor) else np.asarray(labels), device=device)
    except (TypeError, ValueError, RuntimeError) as exc:
        raise ValueError(f"labels must be a 1-D array of integer place ids; could not convert: {exc}") from None
    if labels.ndim != 1 or labels.shape[0] != batch:
        raise ValueError(f"labels must be 1-D with one place id per embedding (length {batch}), "
                         f"got shape {tuple(labels.shape)}")
    if labels.is_floating_point() and not torch.isfinite(labels).all():
        raise ValueError("labels contain NaN or inf; every embedding needs a valid place id")
    if labels.is_complex() or labels.dtype == torch.bool:
        raise ValueError(f"labels must be integer place ids, got dtype {labels.dtype}")
    return labels


def _check_embeddings(embeddings: torch.Tensor) -> torch.Tensor:
    check_tensor(embeddings, "embeddings", ndim=2)
    if embeddings.shape[0] == 0 or embeddings.shape[1] == 0:
        raise ValueError(f"embeddings must be a non-empty (B, D) batch, got shape {tuple(embeddings.shape)}")
    return embeddings


def _all_pair_masks(labels: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Boolean ``(B, B)`` masks of all positive pairs (same label, ``i != j``) and negative pairs."""
    same = labels.unsqueeze(0) == labels.unsqueeze(1)
    eye = torch.eye(labels.shape[0], dtype=torch.bool, device=labels.device)
    return same & ~eye, ~same


def _index_vector(x, name: str, device: torch.device) -> torch.Tensor:
    t = torch.as_tensor(x, device=device)
    if t.ndim != 1:
        raise ValueError(f"miner_pairs: {name} must be a 1-D index tensor, got shape {tuple(t.shape)}")
    if t.numel() == 0:
        return t.long()
    if t.is_floating_point() or t.is_complex() or t.dtype == torch.bool:
        raise ValueError(f"miner_pairs: {name} must hold integer indices, got dtype {t.dtype}")
    return t.long()


def _pair_masks_from_miner(miner_pairs: Sequence, labels: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Boolean ``(B, B)`` masks from a miner's ``(a1, p, a2, n)``, checking every pair against ``labels``."""
    if not isinstance(miner_pairs, (tuple, list)) or len(miner_pairs) != 4:
        raise ValueError("miner_pairs must be the tuple (a1, p, a2, n) returned by multi_similarity_miner, or None")
    batch = labels.shape[0]
    a1, p, a2, n = (_index_vector(x, name, labels.device) for x, name in zip(miner_pairs, ("a1", "p", "a2", "n")))
    if a1.shape != p.shape or a2.shape != n.shape:
        raise ValueError(f"miner_pairs: a1/p and a2/n must have equal lengths, got {len(a1)}/{len(p)} and "
                         f"{len(a2)}/{len(n)}")
    for name, idx in (("a1", a1), ("p", p), ("a2", a2), ("n", n)):
        if idx.numel() and (idx.min() < 0 or idx.max() >= batch):
            raise ValueError(f"miner_pairs: {name} has indices outside [0, {batch}); mine on this same batch")
    if (a1 == p).any() or (labels[a1] != labels[p]).any():
        raise ValueError("miner_pairs: every (a1, p) must be two different embeddings of the same place")
    if (labels[a2] == labels[n]).any():
        raise ValueError("miner_pairs: every (a2, n) must be two embeddings of different places")
    pos = torch.zeros(batch, batch, dtype=torch.bool, device=labels.device)
    neg = torch.zeros_like(pos)
    pos[a1, p] = True
    neg[a2, n] = True
    return pos, neg


def _check_base(base) -> float:
    """The Multi-Similarity threshold lambda as a finite float."""
    try:
        base = float(base)
    except (TypeError, ValueError):
        raise ValueError(f"base (the similarity threshold lambda) must be a number, got {base!r}") from None
    if not np.isfinite(base):
        raise ValueError(f"base (the similarity threshold lambda) must be finite, got {base}")
    return base


def _log_one_plus_sum_exp(x: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Row-wise ``log(1 + sum_{j in mask} exp(x_ij))``, stable: logsumexp with an appended 0."""
    x = x.masked_fill(~mask, float("-inf"))
    zeros = torch.zeros(x.shape[0], 1, dtype=x.dtype, device=x.device)
    return torch.logsumexp(torch.cat([x, zeros], dim=1), dim=1)


# ----------------------------------------------------------------------------------------------
# triplet family (Xiong, Xu, Meng)
# ----------------------------------------------------------------------------------------------
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
# Multi-Similarity (Wang et al., CVPR 2019), as used by SALAD / CliqueMining
# ----------------------------------------------------------------------------------------------
def multi_similarity_loss(embeddings: torch.Tensor, labels, alpha: float = DEFAULT_MS_ALPHA,
                          beta: float = DEFAULT_MS_BETA, base: float = DEFAULT_MS_BASE,
                          miner_pairs: MinerPairs | None = None) -> torch.Tensor:
    """Multi-Similarity loss (Eq. (6) of Wang et al.) on dot-product similarities ``S = E E^T``.

    For each anchor i with positives P_i and negatives N_i (all pairs, or only ``miner_pairs``)::

        L_i = 1/alpha * log(1 + sum_{p in P_i} e^{-alpha (S_ip - base)})
            + 1/beta  * log(1 + sum_{n in N_i} e^{ beta (S_in - base)})

    and the loss is ``sum_i L_i / B``: like pytorch-metric-learning's MeanReducer over its
    per-anchor "element" losses, *every* anchor counts in the mean, an anchor without pairs
    contributing 0 (and one with positives but no mined negatives contributing only its
    positive term). Equal to ``MultiSimilarityLoss(alpha, beta, base, distance=DotProductSimilarity())``
    on L2-normalised embeddings (that PML distance L2-normalises by default; this function does
    not). One difference: PML returns 0 when every index tensor has at most one pair; this
    function still evaluates the formula.
    """
    _check_embeddings(embeddings)
    labels = _check_labels(labels, embeddings.shape[0], embeddings.device)
    alpha = check_positive(alpha, "alpha")
    beta = check_positive(beta, "beta")
    base = _check_base(base)
    if miner_pairs is None:
        pos_mask, neg_mask = _all_pair_masks(labels)
    else:
        pos_mask, neg_mask = _pair_masks_from_miner(miner_pairs, labels)
    sim = embeddings @ embeddings.T
    pos_term = _log_one_plus_sum_exp(-alpha * (sim - base), pos_mask) / alpha
    neg_term = _log_one_plus_sum_exp(beta * (sim - base), neg_mask) / beta
    return (pos_term + neg_term).mean()


def multi_similarity_miner(embeddings: torch.Tensor, labels,
                           epsilon: float = DEFAULT_MS_MINER_EPSILON) -> MinerPairs:
    """Multi-Similarity pair mining (Sec. 3.3 of Wang et al.) on cosine similarities.

    Keeps the negative (i, n) if ``S_in + epsilon > min_p S_ip`` and the positive (i, p) if
    ``S_ip - epsilon < max_n S_in``. Returns ``(a1, p, a2, n)`` LongTensors (positive pairs
    ``(a1[k], p[k])``, negative pairs ``(a2[k], n[k])``), row-major order; the same pairs as
    ``pytorch_metric_learning.miners.MultiSimilarityMiner(epsilon)``. No gradient flows.
    """
    _check_embeddings(embeddings)
    labels = _check_labels(labels, embeddings.shape[0], embeddings.device)
    epsilon = check_positive(epsilon, "epsilon", allow_zero=True)
    with torch.no_grad():
        x = F.normalize(embeddings, p=2, dim=1)
        sim = x @ x.T
        pos_mask, neg_mask = _all_pair_masks(labels)
        hardest_pos = sim.masked_fill(~pos_mask, float("inf")).amin(dim=1, keepdim=True)
        hardest_neg = sim.masked_fill(~neg_mask, float("-inf")).amax(dim=1, keepdim=True)
        a1, p = torch.nonzero(pos_mask & (sim - epsilon < hardest_neg), as_tuple=True)
        a2, n = torch.nonzero(neg_mask & (sim + epsilon > hardest_pos), as_tuple=True)
    return a1, p, a2, n


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


@dataclass(frozen=True)
class MultiSimilarityLoss:
    """Multi-Similarity loss (Wang et al., CVPR 2019, Eq. (6)) over a batch of places, called as
    ``loss(embeddings, labels)``; with ``miner_epsilon`` the pairs are first mined (Sec. 3.3,
    :func:`multi_similarity_miner`), with ``None`` every pair counts (:func:`multi_similarity_loss`).

    ``alpha`` > 0 and ``beta`` > 0 weight the positive and negative pairs, ``base`` is the threshold
    lambda, ``miner_epsilon`` >= 0 or ``None``. The SALAD / GSV-Cities recipe is the default.
    """

    alpha: float = DEFAULT_MS_ALPHA
    beta: float = DEFAULT_MS_BETA
    base: float = DEFAULT_MS_BASE
    miner_epsilon: float | None = DEFAULT_MS_MINER_EPSILON

    def __post_init__(self):
        object.__setattr__(self, "alpha", check_positive(self.alpha, "alpha"))
        object.__setattr__(self, "beta", check_positive(self.beta, "beta"))
        object.__setattr__(self, "base", _check_base(self.base))
        if self.miner_epsilon is not None:
            object.__setattr__(self, "miner_epsilon", check_positive(
                self.miner_epsilon, "miner_epsilon (None: no mining)", allow_zero=True))

    def __call__(self, embeddings: torch.Tensor, labels) -> torch.Tensor:
        pairs = None if self.miner_epsilon is None else multi_similarity_miner(embeddings, labels, self.miner_epsilon)
        return multi_similarity_loss(embeddings, labels, self.alpha, self.beta, self.base, miner_pairs=pairs)


def local_infonce(full: torch.Tensor, shifted: torch.Tensor, offset: int, temperature: float = 0.1,
                  negatives: str = "image", max_anchors: int = 1024, generator: torch.Generator | None = None
                  ) -> torch.Tensor:
    """Local InfoNCE between the feature maps of two horizontally shifted views of the same images.

    ``full`` ``[B, C, h, w]`` is the map of the images, ``shifted`` ``[B, C, h, w']`` the map of the same images
    cropped by ``offset`` feature columns on the left, so that position (i, j) of ``shifted`` sees what position
    (i, j + offset) of ``full`` sees. With every feature L2-normalised, an anchor ``u_a`` at (i, j + offset) of
    ``full`` and its positive ``v_a`` at (i, j) of ``shifted``, the loss is the mean over anchors of

        ℓ_a = −log( exp(u_a·v_a / τ) / Σ_{c ∈ N(a)} exp(u_a·v_c / τ) )                           (L)

    where N(a) holds ``v_a`` and the negatives: every position of the same image's ``shifted`` map
    (``negatives="image"``: a feature must tell its position apart from the rest of its image) or the positives
    of the other anchors, from every image (``"batch"``; at most ``max_anchors`` anchors drawn with ``generator``).
    Minimising it spreads an image's local features apart while keeping them stable under a shift of the view:
    what NetVLAD's and SALAD's assignments need.
    """
    check_tensor(full, "full", ndim=4)
    check_tensor(shifted, "shifted", ndim=4)
    b, c, h, w = full.shape
    offset = int(offset)
    if shifted.shape[:3] != (b, c, h) or not 0 < offset < w:
        raise ValueError(f"shifted must be [B, C, h, w'] like full {tuple(full.shape)} and offset in [1, {w - 1}], "
                         f"got {tuple(shifted.shape)} and offset {offset}")
    check_positive(temperature, "temperature")
    if negatives not in LOCAL_NEGATIVES:
        raise ValueError(f"negatives must be one of {LOCAL_NEGATIVES}, got {negatives!r}")
    overlap = min(w - offset, shifted.shape[3])
    u = F.normalize(full[:, :, :, offset:offset + overlap], dim=1).flatten(2).transpose(1, 2)   # [B, h*ov, C]
    v_all = F.normalize(shifted, dim=1)
    if negatives == "image":
        logits = torch.bmm(u, v_all.flatten(2)) / temperature                                  # [B, h*ov, h*w']
        rows = torch.arange(h, device=full.device).repeat_interleave(overlap)
        cols = torch.arange(overlap, device=full.device).repeat(h)
        target = (rows * shifted.shape[3] + cols).expand(b, -1)
        return F.cross_entropy(logits.flatten(0, 1), target.flatten())
    v = v_all[:, :, :, :overlap].flatten(2).transpose(1, 2)                                     # [B, h*ov, C]
    u, v = u.flatten(0, 1), v.flatten(0, 1)
    keep = torch.randperm(len(u), generator=generator, device=u.device)[:max_anchors] if len(u) > max_anchors else None
    if keep is not None:
        u, v = u[keep], v[keep]
    logits = u @ v.T / temperature
    return F.cross_entropy(logits, torch.arange(len(u), device=u.device))


# The one map from a loss name (the run config's ``source.loss``) to its loss object; each class's parameters
# are named as the run config's source fields (vpr_nb.config.build_loss). A new loss: a class here and a line.
LOSSES = {
    "triplet": TripletLoss,                 # Eq. (3) of DW-T-Loss
    "weighted": WeightedTripletLoss,        # Eq. (4) x Eq. (3), W-T-Loss
    "ce": CETripletLoss,                    # Eqs. (5)-(8), CE-Loss
    "dw": DWTripletLoss,                    # Eq. (9), DW-T-Loss
    "multi-similarity": MultiSimilarityLoss,  # Wang et al. Eq. (6) + miner: the loss of place batches
}
TRIPLET_LOSSES = tuple(k for k, cls in LOSSES.items() if issubclass(cls, TripletFamilyLoss))
