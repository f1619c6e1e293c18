"""Straightforward reference formulations of NetVLAD and SALAD, written from the papers' equations.

They are deliberately naive (a Python loop over clusters, multiplicative Sinkhorn, a ``repeat``-based
aggregation) and serve two purposes only: the equality tests in ``tests/test_aggregation.py`` and the
baselines of ``bench/bench_aggregation.py``. The library versions live in :mod:`vpr_nb.aggregation`.
"""
from __future__ import annotations

from typing import Mapping

import torch
import torch.nn.functional as F


def netvlad_loop_reference(x: torch.Tensor, conv_weight: torch.Tensor, conv_bias: torch.Tensor | None,
                           centroids: torch.Tensor, normalize_input: bool = True) -> torch.Tensor:
    """NetVLAD (Eq. 4 of Arandjelović et al., CVPR 2016) with one residual tensor per cluster.

    For each cluster k: ``V[:, k, :] = Σ_i a_k(x_i)·(x_i − c_k)`` computed from the explicit residual
    tensor ``[B, D, N]``; then intra-normalisation, cluster-major flattening and a global L2.
    """
    if normalize_input:
        x = F.normalize(x, p=2, dim=1)
    batch, dim = x.shape[:2]
    num_clusters = centroids.shape[0]
    local = x.reshape(batch, dim, -1)                                          # [B, D, N]
    assign = F.softmax(F.conv2d(x, conv_weight, conv_bias).reshape(batch, num_clusters, -1), dim=1)
    rows = []
    for k in range(num_clusters):
        residual = local - centroids[k][None, :, None]                         # [B, D, N]
        rows.append((residual * assign[:, k][:, None, :]).sum(dim=2))          # [B, D]
    vlad = torch.stack(rows, dim=1)                                            # [B, K, D]
    vlad = F.normalize(vlad, p=2, dim=2).reshape(batch, -1)
    return F.normalize(vlad, p=2, dim=1)


def sinkhorn_reference(scores: torch.Tensor, dustbin: float | torch.Tensor, num_iters: int) -> torch.Tensor:
    """Transport plan ``P`` ``[B, m+1, n]`` by plain multiplicative Sinkhorn–Knopp scaling.

    Kernel ``K = exp(S̄)`` with the dustbin row appended (shifted by its maximum, which the scalings
    absorb); target row sums ``a = [1]*m + [n−m]`` and column sums ``b = [1]*n``; start from ``v = 1``
    and alternate ``u = a / (K v)``, ``v = b / (Kᵀ u)``; return ``diag(u) K diag(v)``.
    """
    batch, m, n = scores.shape
    dust_row = torch.as_tensor(dustbin).to(scores).reshape(1, 1, 1).expand(batch, 1, n)
    augmented = torch.cat([scores, dust_row], dim=1)
    kernel = torch.exp(augmented - augmented.amax(dim=(1, 2), keepdim=True))
    a = torch.ones(m + 1, dtype=scores.dtype, device=scores.device)
    a[m] = n - m
    b = torch.ones(n, dtype=scores.dtype, device=scores.device)
    v = torch.ones(batch, n, dtype=scores.dtype, device=scores.device)
    for _ in range(num_iters):
        u = a / (kernel * v[:, None, :]).sum(dim=2)
        v = b / (kernel * u[:, :, None]).sum(dim=1)
    return u[:, :, None] * kernel * v[:, None, :]


def salad_reference(params: Mapping[str, torch.Tensor], features: torch.Tensor, token: torch.Tensor,
                    num_iters: int = 3) -> torch.Tensor:
    """DINOv2-SALAD forward in eval mode from a published-layout parameter dict, ``repeat``-based.

    ``params`` uses the checkpoint's key names (``token_features.0.weight``, ``cluster_features.3.bias``,
    ``score.0.weight``, ``dust_bin``, ...); the aggregation is :func:`salad_aggregate_reference`.
    """
    def mlp(prefix: str, last: int, inp: torch.Tensor, layer) -> torch.Tensor:
        hidden = F.relu(layer(inp, params[f"{prefix}.0.weight"], params[f"{prefix}.0.bias"]))
        return layer(hidden, params[f"{prefix}.{last}.weight"], params[f"{prefix}.{last}.bias"])

    f = mlp("cluster_features", 3, features, F.conv2d).flatten(2)              # [B, l, n]
    s = mlp("score", 3, features, F.conv2d).flatten(2)                         # [B, m, n]
    t = mlp("token_features", 2, token, F.linear)                              # [B, token_dim]
    return salad_aggregate_reference(f, s, t, params["dust_bin"], num_iters)


def salad_aggregate_reference(f: torch.Tensor, s: torch.Tensor, t: torch.Tensor,
                              dustbin: float | torch.Tensor, num_iters: int = 3) -> torch.Tensor:
    """SALAD's aggregation of projected features ``f`` ``[B, l, n]``, scores ``s`` ``[B, m, n]``, token ``t``.

    Multiplies the features and the assignment after repeating both to ``[B, l, m, n]``, sums over
    the n positions, intra-normalises, flattens as ``l·m + k`` and prepends the normalised token.
    """
    cluster_dim, num_clusters = f.shape[1], s.shape[1]
    p = sinkhorn_reference(s, dustbin, num_iters)[:, :-1, :]                   # [B, m, n]
    p = p.unsqueeze(1).repeat(1, cluster_dim, 1, 1)                            # [B, l, m, n]
    f = f.unsqueeze(2).repeat(1, 1, num_clusters, 1)                           # [B, l, m, n]
    v = F.normalize((f * p).sum(dim=-1), p=2, dim=1).flatten(1)
    return F.normalize(torch.cat([F.normalize(t, p=2, dim=-1), v], dim=-1), p=2, dim=-1)
