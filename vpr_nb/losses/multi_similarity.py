"""Multi-Similarity (Wang et al., CVPR 2019): the loss of its Eq. (6), the pair miner of its Sec. 3.3, the loss object.

As used to train SALAD and CliqueMining through pytorch-metric-learning: :func:`multi_similarity_loss`,
:func:`multi_similarity_miner` and :class:`MultiSimilarityLoss`, the loss object of place batches
(:class:`vpr_nb.training.PlaceBatchSource`) that holds ``alpha``, ``beta``, ``base`` and ``miner_epsilon``.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np
import torch
import torch.nn.functional as F

from .._checks import check_positive
from ._common import _check_embeddings, _check_labels

# Every default of Multi-Similarity, in one place (the functions' and the loss class's signatures use them).
DEFAULT_MS_ALPHA = 1.0         # Multi-Similarity alpha (positive pairs), Wang et al. Eq. (6)
DEFAULT_MS_BETA = 50.0         # Multi-Similarity beta (negative pairs)
DEFAULT_MS_BASE = 0.0          # Multi-Similarity threshold lambda
DEFAULT_MS_MINER_EPSILON = 0.1 # Multi-Similarity miner margin epsilon (Sec. 3.3); None in a loss: no mining

MinerPairs = tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]


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
