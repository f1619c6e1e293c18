"""The input checks of the loss functions (triplet batches, geo_qp, labels, embeddings) and their reduction.

:func:`_triplet_distances` is the single place where the triplet family (:mod:`vpr_nb.losses.triplet`)
measures the plain Euclidean distances ``d(q,p)`` and ``d(q,n)`` of Eqs. (3)-(9); :func:`_reduce` applies
the ``reduction`` (the paper's ``"sum"``, ``"mean"`` or ``"none"``) to the per-triplet losses.
"""
from __future__ import annotations

import numpy as np
import torch

from .._checks import check_tensor

_REDUCTIONS = ("sum", "mean", "none")


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
