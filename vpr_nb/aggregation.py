"""Aggregation layers: from a local feature map ``[B, C, H, W]`` to one global descriptor.

Every aggregator is an :class:`torch.nn.Module` whose output is an L2-normalised ``[B, out_dim]``
descriptor, so that Euclidean and cosine retrieval give the same ranking.

- :class:`MaxPool`, :class:`MeanPool`, :class:`GeM`: global pooling (Radenović et al., TPAMI 2018).
- :class:`NetVLAD`: soft-assignment VLAD (Arandjelović et al., CVPR 2016), parameter names compatible
  with the widely used ``Nanne/pytorch-NetVlad`` checkpoints; :func:`kmeans_centroids`,
  :func:`sample_local_descriptors` and :meth:`NetVLAD.init_from_clusters` do its k-means initialisation.
- :class:`SALAD`, :func:`salad_aggregate` and :func:`sinkhorn`: optimal-transport aggregation
  (Izquierdo & Civera, CVPR 2024); parameter names compatible with the published DINOv2-SALAD checkpoint.
- :func:`make_aggregator`: build any of them by name.
"""
from __future__ import annotations

import inspect
import math

import faiss
import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from ._checks import (_inputs_validated, as_float_matrix, check_int, check_positive, check_tensor, tensor_is_finite,
                      validated_inputs)
from ._threads import single_threaded_call
from .pointwise import PointwiseConv2d

def _check_feature_map(x: torch.Tensor, name: str, channels: int | None, finite: bool = True) -> torch.Tensor:
    """Validate a non-empty floating ``[B, C, H, W]`` map whose ``C`` equals ``channels`` (if given);
    ``finite=False`` leaves the NaN/inf check to the caller."""
    check_tensor(x, name, ndim=4, finite=finite)
    if x.shape[0] == 0 or x.shape[2] == 0 or x.shape[3] == 0:
        raise ValueError(f"{name} is empty (shape {tuple(x.shape)}): it needs at least one image and one position")
    if channels is not None and x.shape[1] != channels:
        raise ValueError(f"{name} has {x.shape[1]} channels but this layer was built for {channels}; "
                         f"build it with the backbone's output channel count")
    return x


class _GlobalPool(nn.Module):
    """Shared skeleton of the pooling layers: validate, pool to ``[B, C]``, L2-normalise."""

    needs_token = False  # forward takes the feature map alone

    def __init__(self, in_channels: int | None = None) -> None:
        super().__init__()
        self.in_channels = None if in_channels is None else check_int(in_channels, "in_channels")
        self.out_dim = self.in_channels  # None until the channel count is known

    def _pool(self, x: torch.Tensor) -> torch.Tensor:
        raise NotImplementedError

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """``x``: ``[B, C, H, W]`` feature map → L2-normalised ``[B, C]`` descriptor."""
        _check_feature_map(x, "x", self.in_channels)
        return F.normalize(self._pool(x), p=2, dim=1)


class MaxPool(_GlobalPool):
    """MAC: per-channel maximum over positions, Eq. (1) of Radenović et al. (TPAMI 2018), then L2.

    ``in_channels`` is optional; when given it sets ``out_dim`` and is checked in ``forward``.
    """

    def _pool(self, x: torch.Tensor) -> torch.Tensor:
        return x.amax(dim=(2, 3))


class MeanPool(_GlobalPool):
    """SPoC: per-channel mean over positions, Eq. (2) of Radenović et al. (TPAMI 2018), then L2."""

    def _pool(self, x: torch.Tensor) -> torch.Tensor:
        return x.mean(dim=(2, 3))


class GeM(_GlobalPool):
    """Generalised-mean pooling ``(mean_i x_i^p)^(1/p)``, Eq. (3) of Radenović et al. (TPAMI 2018), then L2.

    Activations are clamped at ``eps`` so that the power is defined. ``p`` is an ``nn.Parameter`` of
    shape ``[1]`` named ``p`` (the layout of common GeM checkpoints), trainable iff ``learnable``.
    ``p = 1`` is mean pooling, ``p → ∞`` tends to max pooling.
    """

    def __init__(self, p: float = 3.0, eps: float = 1e-6, learnable: bool = True,
                 in_channels: int | None = None) -> None:
        super().__init__(in_channels)
        if not isinstance(learnable, bool):
            raise ValueError(f"learnable must be True or False, got {learnable!r}")
        self.p = nn.Parameter(torch.tensor([check_positive(p, "p")]), requires_grad=learnable)
        self.eps = check_positive(eps, "eps")

    def _pool(self, x: torch.Tensor) -> torch.Tensor:
        p = self.p.to(x.dtype)
        return x.clamp(min=self.eps).pow(p).mean(dim=(2, 3)).pow(1.0 / p)


# ----------------------------------------------------------------------------------------- NetVLAD


class NetVLAD(nn.Module):
    """NetVLAD layer, Eq. (4) of Arandjelović et al. (CVPR 2016), vectorised over clusters.

    For local descriptors ``x_i`` (optionally L2-normalised first), soft assignments
    ``a_k(x_i) = softmax_k(w_k·x_i + b_k)`` (Eq. 3) weight the residuals to the centroids:
    ``V[k, :] = Σ_i a_k(x_i) (x_i − c_k) = (Σ_i a_k(x_i) x_i) − (Σ_i a_k(x_i)) c_k``; each row of ``V``
    is L2-normalised (intra-normalisation, Arandjelović & Zisserman CVPR 2013), ``V`` is flattened
    cluster-major (index ``k·D + d``) and L2-normalised again. Output size ``num_clusters·dim``.

    Parameters ``conv.weight`` ``[K, D, 1, 1]``, ``conv.bias`` ``[K]`` (only if ``vladv2``) and
    ``centroids`` ``[K, D]`` have the names of ``Nanne/pytorch-NetVlad`` so its checkpoints load with
    ``load_state_dict``. Initial values come from torch's global RNG (seed it, e.g. with
    :func:`vpr_nb.seed_everything`); call :meth:`init_from_clusters` for the k-means initialisation.
    """

    needs_token = False  # forward takes the feature map alone

    def __init__(self, num_clusters: int = 64, dim: int = 512, normalize_input: bool = True,
                 vladv2: bool = False) -> None:
        super().__init__()
        for flag, flag_name in ((normalize_input, "normalize_input"), (vladv2, "vladv2")):
            if not isinstance(flag, bool):
                raise ValueError(f"{flag_name} must be True or False, got {flag!r}")
        self.num_clusters = check_int(num_clusters, "num_clusters")
        self.dim = check_int(dim, "dim")
        self.normalize_input = normalize_input
        self.vladv2 = vladv2
        self.alpha = 0.0
        self.out_dim = self.num_clusters * self.dim
        self.conv = PointwiseConv2d(self.dim, self.num_clusters, bias=vladv2)
        self.centroids = nn.Parameter(torch.rand(self.num_clusters, self.dim))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """``x``: ``[B, D, H, W]`` feature map → L2-normalised ``[B, K·D]`` NetVLAD descriptor."""
        _check_feature_map(x, "x", self.dim, finite=not self.normalize_input)
        if self.normalize_input:   # F.normalize(x, dim=1), whose per-position norms also tell whether x is finite
            norm = x.norm(2, 1, keepdim=True)                                # [B, 1, H, W]
            if not (_inputs_validated() or tensor_is_finite(norm)):
                check_tensor(x, "x")   # raises on NaN/inf (finite values whose squares overflow pass)
            x = x / norm.clamp_min(1e-12).expand_as(x)
        assign = F.softmax(self.conv(x).flatten(2), dim=1)                  # [B, K, N]
        weighted_sum = torch.bmm(assign, x.flatten(2).transpose(1, 2))      # [B, K, D]: Σ_i a_k x_i
        mass = assign.sum(dim=2, keepdim=True)                              # [B, K, 1]: Σ_i a_k
        vlad = weighted_sum - mass * self.centroids.to(x.dtype)
        vlad = F.normalize(vlad, p=2, dim=2).flatten(1)
        return F.normalize(vlad, p=2, dim=1)

    @single_threaded_call   # numpy products on one BLAS thread (vpr_nb._threads)
    def init_from_clusters(self, centroids, descriptors) -> None:
        """Initialise the layer from k-means ``centroids`` ``[K, D]`` and sample ``descriptors`` ``[N, D]``.

        Sets ``alpha`` so that on average the best cluster gets 100× the assignment weight of the
        second best (``exp(α·Δ) = 100``, i.e. ``α = −log(0.01) / mean Δ``), as in the NetVLAD code:

        - v1 (``vladv2=False``): Δ = best − second-best cosine similarity between a descriptor and the
          L2-normalised centroids ĉ_k; ``conv.weight = α·ĉ_k`` (the "b_k = 0" variant of the paper's code).
        - v2: Δ = d₂² − d₁², the squared Euclidean distances to the two nearest centroids;
          ``conv.weight = 2α·c_k`` and ``conv.bias = −α‖c_k‖²`` (Eq. 3 of the paper), so the logits are
          ``−α‖x − c_k‖²`` up to a per-descriptor constant (Eq. 2).

        In both cases the ``centroids`` parameter is set to ``centroids``. Accepts numpy or torch. Pass
        the descriptors the layer sees (L2-normalised ones, e.g. from :func:`sample_local_descriptors`,
        when ``normalize_input``).
        """
        cents = as_float_matrix(centroids, "centroids", dim=self.dim).astype(np.float64)
        descs = as_float_matrix(descriptors, "descriptors", dim=self.dim).astype(np.float64)
        if cents.shape[0] != self.num_clusters:
            raise ValueError(f"centroids has {cents.shape[0]} rows but the layer has num_clusters="
                             f"{self.num_clusters}; run k-means with that many clusters")
        self.alpha = netvlad_alpha(cents, descs, self.vladv2)
        with torch.no_grad():
            cent_t = torch.from_numpy(cents)
            if self.vladv2:
                self.conv.weight.copy_((2 * self.alpha * cent_t)[:, :, None, None])
                self.conv.bias.copy_(-self.alpha * (cent_t ** 2).sum(1))
            else:
                unit = cent_t / cent_t.norm(dim=1, keepdim=True)
                self.conv.weight.copy_((self.alpha * unit)[:, :, None, None])
            self.centroids.copy_(cent_t)


@single_threaded_call   # numpy products on one BLAS thread (vpr_nb._threads)
def netvlad_alpha(centroids: np.ndarray, descriptors: np.ndarray, vladv2: bool = False) -> float:
    """NetVLAD's α (:meth:`NetVLAD.init_from_clusters`): ``−log(0.01) / mean Δ`` with Δ the gap between a
    descriptor's best and second-best cluster (v1: cosine similarities; v2: squared distances), so that on
    average the best cluster gets 100× the second's weight. float64 numpy ``[K, D]`` and ``[N, D]``, K ≥ 2."""
    cents, descs = np.asarray(centroids, dtype=np.float64), np.asarray(descriptors, dtype=np.float64)
    if cents.shape[0] < 2:
        raise ValueError("init_from_clusters needs at least 2 clusters (alpha compares the best "
                         "and the second-best cluster)")
    if vladv2:
        sq_dist = (descs ** 2).sum(1, keepdims=True) - 2 * descs @ cents.T + (cents ** 2).sum(1)
        two_nearest = np.sort(sq_dist, axis=1)[:, :2]
        gap = float(np.mean(two_nearest[:, 1] - two_nearest[:, 0]))
    else:
        cent_norms = np.linalg.norm(cents, axis=1, keepdims=True)
        if (cent_norms == 0).any():
            raise ValueError("centroids contains an all-zero row: it has no direction for the "
                             "cosine assignment; re-run k-means or drop the empty cluster")
        desc_norms = np.linalg.norm(descs, axis=1, keepdims=True)
        if (desc_norms == 0).any():
            raise ValueError("descriptors contains an all-zero row; drop it before initialising")
        cos = (descs / desc_norms) @ (cents / cent_norms).T
        two_best = -np.sort(-cos, axis=1)[:, :2]
        gap = float(np.mean(two_best[:, 0] - two_best[:, 1]))
    if not gap > 0:
        raise ValueError("every descriptor is equally close to its two nearest centroids, so alpha "
                         "is undefined; use distinct centroids (e.g. from kmeans_centroids)")
    return float(-np.log(0.01) / gap)


def sample_local_descriptors(feature_maps: torch.Tensor, per_image: int, seed: int = 0,
                             skip_zero: bool = True) -> np.ndarray:
    """Draw ``per_image`` distinct positions of each map in ``[N, C, H, W]``, as NetVLAD's cluster step.

    Returns an L2-normalised float32 ``[M, C]`` numpy array (image-major), ready for
    :func:`kmeans_centroids`. Positions are drawn without replacement by ``np.random.default_rng(seed)``.

    A local feature that is exactly zero (a backbone ending in a ReLU switches whole positions off)
    has no direction, so it cannot be L2-normalised nor assigned to a centroid by cosine. With
    ``skip_zero`` (the default) such positions are never drawn: each image gives ``per_image``
    non-zero features, or all it has if fewer, so ``M ≤ N·per_image``; on maps without zero
    features the draw is the same as without ``skip_zero`` and ``M = N·per_image``. With
    ``skip_zero=False`` zero features are kept (as zero rows). Raises if every feature is zero.
    """
    _check_feature_map(feature_maps, "feature_maps", None)
    if not isinstance(skip_zero, bool):
        raise ValueError(f"skip_zero must be True or False, got {skip_zero!r}")
    n, c, h, w = feature_maps.shape
    per_image = check_int(per_image, "per_image", maximum=h * w)
    seed = check_int(seed, "seed", minimum=0)
    rng = np.random.default_rng(seed)
    keys = rng.random((n, h * w))
    flat = feature_maps.detach().flatten(2).transpose(1, 2)                            # [N, HW, C]
    if skip_zero:
        nonzero = (flat != 0).any(dim=2).cpu().numpy()                                 # [N, HW]
        if not nonzero.any():
            raise ValueError("every local feature of feature_maps is exactly zero: there is nothing to cluster "
                             "(check the backbone, e.g. a dead final ReLU)")
        keys[~nonzero] = np.inf                                                        # zero features sort last
    positions = np.argsort(keys, axis=1, kind="stable")[:, :per_image]                 # [N, per_image]
    picked = torch.gather(flat, 1, torch.from_numpy(positions).to(flat.device)[:, :, None].expand(-1, -1, c))
    picked = picked.reshape(n * per_image, c)
    if skip_zero:
        picked = picked[torch.from_numpy(np.take_along_axis(nonzero, positions, axis=1).reshape(-1)).to(picked.device)]
    picked = F.normalize(picked.float(), p=2, dim=1)
    return picked.cpu().numpy()


@single_threaded_call   # faiss's BLAS and OpenMP loops on one thread (vpr_nb._threads)
def kmeans_centroids(descriptors, num_clusters: int, niter: int = 100, seed: int = 0) -> np.ndarray:
    """k-means centroids ``[num_clusters, D]`` (float32) of ``descriptors`` ``[N, D]`` with ``faiss.Kmeans``.

    The faiss seed makes the result deterministic. ``num_clusters`` must not exceed N; faiss warns
    (but works) with fewer than 39 points per centroid.
    """
    descs = as_float_matrix(descriptors, "descriptors")
    num_clusters = check_int(num_clusters, "num_clusters")
    if num_clusters > descs.shape[0]:
        raise ValueError(f"cannot form {num_clusters} clusters from {descs.shape[0]} descriptors; "
                         f"sample more descriptors or use fewer clusters")
    niter = check_int(niter, "niter")
    seed = check_int(seed, "seed", minimum=0)
    kmeans = faiss.Kmeans(descs.shape[1], num_clusters, niter=niter, seed=seed, verbose=False)
    kmeans.train(descs)
    return np.ascontiguousarray(kmeans.centroids, dtype=np.float32)


# ------------------------------------------------------------------------------------------- SALAD


def _as_scalar_tensor(value: torch.Tensor | float, name: str) -> torch.Tensor:
    """Return a finite real scalar (a one-element tensor or a Python number) as a tensor."""
    if isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, bool):
        value = torch.tensor(float(value))
    if not isinstance(value, torch.Tensor) or value.numel() != 1:
        shape = tuple(value.shape) if isinstance(value, torch.Tensor) else type(value).__name__
        raise ValueError(f"{name} must be a scalar (a number or a one-element tensor), got {shape}")
    return check_tensor(value, name)


def sinkhorn(scores: torch.Tensor, dustbin: torch.Tensor | float, num_iters: int = 3) -> torch.Tensor:
    """Log-space Sinkhorn (regularisation 1) with a dustbin row: SALAD's optimal-transport assignment.

    ``scores`` ``[B, m, n]`` (m clusters, n features) is augmented with a row holding ``dustbin`` in
    every column, giving ``S̄`` ``[B, m+1, n]``. Sinkhorn (Cuturi 2013) alternates the row and column
    log-scalings ``u, v`` of ``exp(S̄)`` towards the marginals ``a = [1]*m + [n−m]`` (each cluster
    receives mass 1, the dustbin the rest) and ``b = [1]*n`` (each feature distributes mass 1). As in
    the published code both marginals are divided by ``n+m`` during the iterations and ``log(n+m)`` is
    added back at the end. Returns the log transport plan ``log P`` ``[B, m+1, n]`` (dustbin last).
    Needs ``n > m``. A scalar ``dustbin`` (SALAD's one learned score) cancels in the first row update, so
    the plan does not depend on it and it gets no gradient (notebook 05 measures both).
    """
    check_tensor(scores, "scores", ndim=3)
    dustbin = _as_scalar_tensor(dustbin, "dustbin")
    num_iters = check_int(num_iters, "num_iters")
    batch, m, n = scores.shape
    if batch == 0 or m == 0:
        raise ValueError(f"scores is empty (shape {tuple(scores.shape)}): it needs at least one image and one cluster")
    if n <= m:
        side = math.isqrt(m) + 1
        raise ValueError(f"{m} clusters need more than {m} feature positions (got n={n}), i.e. at least a "
                         f"{side}×{side} map; use fewer clusters or larger images")
    dust_row = dustbin.to(scores.dtype).reshape(1, 1, 1).expand(batch, 1, n)
    log_k = torch.cat([scores, dust_row], dim=1)                                    # [B, m+1, n]
    norm = -math.log(n + m)
    log_a = torch.full((m + 1,), norm, dtype=scores.dtype, device=scores.device)
    log_a[m] = norm + math.log(n - m)
    log_b = torch.full((n,), norm, dtype=scores.dtype, device=scores.device)
    u = torch.zeros(batch, m + 1, dtype=scores.dtype, device=scores.device)
    v = torch.zeros(batch, n, dtype=scores.dtype, device=scores.device)
    for _ in range(num_iters):
        u = log_a - torch.logsumexp(log_k + v[:, None, :], dim=2)
        v = log_b - torch.logsumexp(log_k + u[:, :, None], dim=1)
    return log_k + u[:, :, None] + v[:, None, :] - norm


SALAD_ASSIGNMENTS = ("sinkhorn", "softmax")


def salad_aggregate(local_features: torch.Tensor, scores: torch.Tensor, token: torch.Tensor,
                    dustbin: torch.Tensor | float, num_iters: int = 3, assignment: str = "sinkhorn") -> torch.Tensor:
    """SALAD's aggregation step (Izquierdo & Civera, CVPR 2024, Sec. 3) on already projected inputs.

    ``local_features`` ``f`` ``[B, l, n]``, ``scores`` ``s`` ``[B, m, n]`` and the projected global
    token ``[B, d]`` give ``L2([L2(token), V])`` with ``P = exp(sinkhorn(s, dustbin))`` minus its
    dustbin row and ``V[l, k] = Σ_i f[l, i]·P[k, i]`` (one batched product ``f·Pᵀ``, no
    ``[B, l, m, n]`` tensor), each cluster column L2-normalised over l and flattened as ``l·m + k``.
    Output ``[B, d + l·m]``. ``assignment="softmax"`` (the mechanism's ablation) replaces the plan by
    ``P = softmax_k(s)``: each feature's unit of mass spread over the clusters on its own, NetVLAD's way, with
    no dustbin and no cluster marginal (``dustbin`` and ``num_iters`` are then unused).
    """
    if assignment not in SALAD_ASSIGNMENTS:
        raise ValueError(f"assignment must be one of {SALAD_ASSIGNMENTS}, got {assignment!r}")
    check_tensor(local_features, "local_features", ndim=3)
    check_tensor(token, "token", ndim=2)
    check_tensor(scores, "scores", ndim=3)
    dustbin = _as_scalar_tensor(dustbin, "dustbin")
    batch, _, n = local_features.shape
    if scores.shape[0] != batch or scores.shape[2] != n or token.shape[0] != batch:
        raise ValueError(f"local_features {tuple(local_features.shape)}, scores {tuple(scores.shape)} and token "
                         f"{tuple(token.shape)} must share the batch size B (and n for the first two)")
    if assignment == "softmax":
        p = torch.softmax(scores, dim=1)                                          # [B, m, n], columns sum to 1
    else:
        with validated_inputs():    # sinkhorn gets the scores and dustbin checked above
            p = torch.exp(sinkhorn(scores, dustbin, num_iters))[:, :-1, :]       # [B, m, n]
    v = torch.bmm(local_features, p.transpose(1, 2).to(local_features.dtype))     # [B, l, m]
    v = F.normalize(v, p=2, dim=1).flatten(1)
    return F.normalize(torch.cat([F.normalize(token, p=2, dim=-1), v], dim=-1), p=2, dim=-1)


class SALAD(nn.Module):
    """SALAD aggregator (Izquierdo & Civera, CVPR 2024, Sec. 3), state-dict compatible with DINOv2-SALAD.

    From local features ``x`` ``[B, C, H, W]`` (n = H·W positions) and the global token ``t`` ``[B, C]``:

    - ``f = cluster_features(x)`` ``[B, l, n]`` (l = ``cluster_dim``): projected local features;
    - ``s = score(x)`` ``[B, m, n]`` (m = ``num_clusters``): feature-to-cluster scores;
    - :func:`salad_aggregate`: ``P = exp(sinkhorn(s, dust_bin, 3))`` without its dustbin row
      (optimal-transport assignment), ``V[l, k] = Σ_i f[l, i]·P[k, i]`` (no centroid residual, unlike
      NetVLAD), each cluster column L2-normalised over l, flattened in the published order (``l·m + k``);
    - output ``L2([L2(token_features(t)), V])`` of size ``token_dim + m·l`` (8448 with the defaults).

    ``V`` is one batched matrix product ``f·Pᵀ``, so no ``[B, l, m, n]`` tensor is materialised.
    ``hidden_dim`` is the width of the three MLP heads (512 in the published model, whose checkpoint
    needs the default; a smaller width suits small backbones such as :class:`vpr_nb.models.SmallCNN`).
    Initial weights come from torch's global RNG (seed it, e.g. with :func:`vpr_nb.seed_everything`).
    ``assignment="softmax"`` runs the same head without optimal transport (:func:`salad_aggregate`): the
    mechanism's ablation; the default ``"sinkhorn"`` is the paper's.
    """

    needs_token = True  # forward takes the pair (feature map, global token)

    def __init__(self, num_channels: int = 768, num_clusters: int = 64, cluster_dim: int = 128,
                 token_dim: int = 256, dropout: float = 0.3, hidden_dim: int = 512,
                 assignment: str = "sinkhorn") -> None:
        super().__init__()
        if assignment not in SALAD_ASSIGNMENTS:
            raise ValueError(f"assignment must be one of {SALAD_ASSIGNMENTS}, got {assignment!r}")
        self.assignment = assignment
        self.num_channels = check_int(num_channels, "num_channels")
        self.num_clusters = check_int(num_clusters, "num_clusters")
        self.cluster_dim = check_int(cluster_dim, "cluster_dim")
        self.token_dim = check_int(token_dim, "token_dim")
        self.hidden_dim = check_int(hidden_dim, "hidden_dim")
        dropout = check_positive(dropout, "dropout", allow_zero=True)
        if dropout >= 1:
            raise ValueError(f"dropout must be in [0, 1), got {dropout}")
        self.out_dim = self.token_dim + self.num_clusters * self.cluster_dim
        hidden = self.hidden_dim
        self.token_features = nn.Sequential(
            nn.Linear(self.num_channels, hidden), nn.ReLU(), nn.Linear(hidden, self.token_dim))
        self.cluster_features = nn.Sequential(
            PointwiseConv2d(self.num_channels, hidden), nn.Dropout(dropout), nn.ReLU(),
            PointwiseConv2d(hidden, self.cluster_dim))
        self.score = nn.Sequential(
            PointwiseConv2d(self.num_channels, hidden), nn.Dropout(dropout), nn.ReLU(),
            PointwiseConv2d(hidden, self.num_clusters))
        self.dust_bin = nn.Parameter(torch.tensor(1.0))

    def forward(self, x: tuple[torch.Tensor, torch.Tensor]) -> torch.Tensor:
        """``x = (features [B, C, H, W], token [B, C])`` → L2-normalised ``[B, out_dim]`` descriptor."""
        if not isinstance(x, (tuple, list)) or len(x) != 2:
            raise ValueError("SALAD takes a pair (features [B, C, H, W], token [B, C]), as the DINOv2 "
                             f"backbone returns; got {type(x).__name__}")
        features, token = x
        _check_feature_map(features, "features", self.num_channels)
        check_tensor(token, "token", ndim=2)
        if token.shape != (features.shape[0], self.num_channels):
            raise ValueError(f"token must have shape ({features.shape[0]}, {self.num_channels}) to match "
                             f"features {tuple(features.shape)}, got {tuple(token.shape)}")
        f = self.cluster_features(features).flatten(2)                              # [B, l, n]
        s = self.score(features).flatten(2)                                          # [B, m, n]
        with validated_inputs():    # f, s and the token come from the inputs checked above
            return salad_aggregate(f, s, self.token_features(token), self.dust_bin, 3, self.assignment)

    def standardise_inputs(self, mean, std) -> None:
        """Fold ``x -> (x - mean) / std`` (per channel) into the first 1×1 conv of the score and cluster-feature
        heads, so that they see standardised local features; the token head and the state-dict layout are
        unchanged. A data-dependent initialisation (NetVLAD's k-means plays this role): on a backbone whose
        local features share a large common component the published initialisation gives identical cluster
        vectors (notebook 05); :func:`vpr_nb.models.init_salad` computes ``mean`` and ``std`` from images."""
        mean = torch.as_tensor(mean, dtype=torch.float32).flatten()
        std = torch.as_tensor(std, dtype=torch.float32).flatten()
        for name, t in (("mean", mean), ("std", std)):
            if t.shape != (self.num_channels,) or not torch.isfinite(t).all():
                raise ValueError(f"{name} must hold {self.num_channels} finite values (one per channel), "
                                 f"got shape {tuple(t.shape)}")
        if not (std > 0).all():
            raise ValueError("std must be positive in every channel (clamp it, e.g. std.clamp_min(1e-3))")
        with torch.no_grad():
            for head in (self.score, self.cluster_features):
                conv = head[0]
                conv.bias -= conv.weight[:, :, 0, 0] @ (mean / std).to(conv.weight)
                conv.weight /= std.to(conv.weight)[None, :, None, None]


# ----------------------------------------------------------------------------------------- factory


_FACTORY: dict[str, tuple[type[nn.Module], str]] = {
    "max": (MaxPool, "in_channels"), "mean": (MeanPool, "in_channels"), "gem": (GeM, "in_channels"),
    "netvlad": (NetVLAD, "dim"), "salad": (SALAD, "num_channels"),
}
AGGREGATOR_NAMES = tuple(_FACTORY)
# the constructor argument of each aggregator that make_aggregator fills with the backbone's channel count
CHANNEL_ARGUMENTS = {name: arg for name, (_, arg) in _FACTORY.items()}


def make_aggregator(name: str, in_channels: int, **kwargs) -> nn.Module:
    """Build an aggregator by ``name`` (one of :data:`AGGREGATOR_NAMES`) for ``in_channels`` channels.

    ``kwargs`` go to the class: e.g. ``make_aggregator("gem", 512, p=3.0)``,
    ``make_aggregator("netvlad", 512, num_clusters=16)``. For ``"salad"`` the module's ``forward``
    takes the pair ``(features, token)``.
    """
    if not isinstance(name, str) or name.lower() not in _FACTORY:
        raise ValueError(f"unknown aggregator {name!r}; valid names are {', '.join(AGGREGATOR_NAMES)}")
    cls, channel_arg = _FACTORY[name.lower()]
    in_channels = check_int(in_channels, "in_channels")
    allowed = [a for a in inspect.signature(cls).parameters if a != channel_arg]
    unknown = sorted(set(kwargs) - set(allowed))
    if unknown:
        raise ValueError(f"{cls.__name__} does not take {', '.join(unknown)}; its options are {', '.join(allowed)}")
    return cls(**{channel_arg: in_channels}, **kwargs)
