"""The data-driven initialisations of the aggregator heads: NetVLAD's k-means, SALAD's standardised inputs and
SALAD's score head from NetVLAD's k-means centroids (so that both start level)."""
from __future__ import annotations

import numpy as np
import torch

from .._checks import as_float_matrix, check_int, check_positive
from ..aggregation import SALAD, NetVLAD, kmeans_centroids, netvlad_alpha, sample_local_descriptors
from ..image_tensors import as_image_array, images_to_tensor
from .vpr_model import VPRModel


def init_netvlad(model: "VPRModel", images, per_image: int = 20, niter: int = 50, seed: int = 0,
                 batch_size: int = 256, max_images: int | None = None):
    """NetVLAD's cluster step for a :class:`VPRModel` with a NetVLAD aggregator.

    Runs the backbone over ``images`` (uint8 ``(N, H, W, 3)``, e.g. the training database), samples
    ``per_image`` L2-normalised local descriptors per image (from at most ``max_images`` images drawn
    at random; pytorch-NetVlad uses 50 000 descriptors, 100 per image), runs faiss k-means with K = the layer's
    ``num_clusters`` and calls ``init_from_clusters`` (centroids and α, Eq. (6) of notebook 04).
    Local features that are exactly zero (positions a final ReLU switched off, common in a trained
    backbone) have no direction and are never sampled (:func:`vpr_nb.aggregation.sample_local_descriptors`
    with ``skip_zero=True``), so an image contributes fewer than ``per_image`` descriptors when it has
    fewer non-zero ones. Returns ``(descriptors, centroids)``. Deterministic for a given ``seed``.
    """
    if not isinstance(getattr(model, "aggregator", None), NetVLAD):
        raise ValueError("init_netvlad needs a VPRModel whose aggregator is NetVLAD "
                         "(build_model(..., 'netvlad', num_clusters=K))")
    maps = _backbone_maps(model, images, seed, batch_size, max_images)
    descs = sample_local_descriptors(maps, per_image, seed=seed, skip_zero=True)
    cents = kmeans_centroids(descs, model.aggregator.num_clusters, niter=niter, seed=seed)
    model.aggregator.init_from_clusters(cents, descs)
    return descs, cents


def _backbone_maps(model: "VPRModel", images, seed: int, batch_size: int, max_images: int | None) -> torch.Tensor:
    """The backbone's feature maps of ``images`` (at most ``max_images`` of them, drawn with ``seed``)."""
    arr = as_image_array(images)
    if max_images is not None and len(arr) > check_int(max_images, "max_images"):
        arr = arr[np.sort(np.random.default_rng(seed).choice(len(arr), max_images, replace=False))]
    maps = []
    with torch.no_grad():
        for start in range(0, len(arr), batch_size):
            maps.append(model.backbone(images_to_tensor(arr[start:start + batch_size])))
    return torch.cat(maps)


def salad_scores_from_centroids(salad: SALAD, centroids, alpha: float) -> None:
    """Set SALAD's score head to NetVLAD's v1 logits ``s_k(x) = α·ĉ_k·x`` (ĉ_k: the L2-normalised ``centroids``
    ``[m, C]``; Eq. (3) of Arandjelović et al. with b_k = 0).

    The head is ``conv2(ReLU(dropout(conv1(x))))`` (hidden width ≥ 2m needed): units k and m+k of ``conv1``
    get ``±α·ĉ_k`` (no bias) and ``conv2`` adds the first and subtracts the second, so that
    ``ReLU(z) − ReLU(−z) = z`` gives the logits exactly (in eval mode; in training the head's dropout perturbs
    them). The other hidden units keep their weights, and ``conv2`` gives them weight 0: they start silent
    but still train. Everything else (the cluster features, the token head, the dustbin) is unchanged."""
    if not isinstance(salad, SALAD):
        raise ValueError(f"salad_scores_from_centroids needs a SALAD aggregator, got {type(salad).__name__}")
    m, c = salad.num_clusters, salad.num_channels
    cents = torch.from_numpy(as_float_matrix(centroids, "centroids", dim=c).astype(np.float64))
    if cents.shape[0] != m:
        raise ValueError(f"centroids has {cents.shape[0]} rows but SALAD has num_clusters={m}")
    if salad.hidden_dim < 2 * m:
        raise ValueError(f"the score head needs hidden_dim >= 2 x num_clusters = {2 * m} to hold the centroids' "
                         f"logits exactly, got hidden_dim={salad.hidden_dim}")
    norms = cents.norm(dim=1, keepdim=True)
    if (norms == 0).any():
        raise ValueError("centroids contains an all-zero row: it has no direction; re-run k-means")
    alpha = check_positive(alpha, "alpha")
    conv1, conv2 = salad.score[0], salad.score[-1]
    with torch.no_grad():
        w = (alpha * cents / norms).to(conv1.weight)
        conv1.weight[:2 * m] = torch.cat([w, -w])[:, :, None, None]
        conv1.bias[:2 * m] = 0
        eye = torch.eye(m, dtype=conv2.weight.dtype)
        conv2.weight.zero_()
        conv2.weight[:, :2 * m] = torch.cat([eye, -eye], 1)[:, :, None, None]
        conv2.bias.zero_()


def init_salad_scores_from_kmeans(model: "VPRModel", images, centroids=None, per_image: int = 20, niter: int = 50,
                                  seed: int = 0, batch_size: int = 256,
                                  max_images: int | None = None, temperature: float = 1.0) -> tuple[np.ndarray, float]:
    """Start SALAD's score head where NetVLAD starts: from k-means centroids of the local features.

    Untrained, SALAD's scores are a random MLP's, near uniform and collapsed (notebook 05), while NetVLAD
    starts from k-means (:func:`init_netvlad`): compared from their own starts, the two methods differ by
    their initialisation as much as by their mechanism. This gives SALAD NetVLAD's start. With ``centroids``
    ``None`` it samples descriptors and runs k-means exactly as :func:`init_netvlad` does with the same
    arguments (the same centroids on the same backbone and images), or takes the given ``centroids`` ``[m, C]``
    (e.g. a NetVLAD start's). α is NetVLAD's (:func:`vpr_nb.aggregation.netvlad_alpha`, v1), divided by the
    mean norm of the non-zero local features: SALAD's head sees them unnormalised, so a feature of mean norm
    gets NetVLAD's logits exactly. Sets the head with :func:`salad_scores_from_centroids`; run it after
    :func:`init_salad` (which it overrides for the score head's first 2m units). ``temperature`` > 0 divides
    the logits (α / temperature): above 1 the start's assignment is softer (notebook 05 levels two
    assignments' starts with it). Returns
    ``(centroids, alpha)``, the α set in the head. Deterministic for a given ``seed``.
    """
    if not isinstance(getattr(model, "aggregator", None), SALAD):
        raise ValueError("init_salad_scores_from_kmeans needs a VPRModel whose aggregator is SALAD "
                         "(build_model(..., 'salad'))")
    maps = _backbone_maps(model, images, seed, check_int(batch_size, "batch_size"), max_images)
    descs = sample_local_descriptors(maps, per_image, seed=seed, skip_zero=True)
    m = model.aggregator.num_clusters
    if centroids is None:
        centroids = kmeans_centroids(descs, m, niter=niter, seed=seed)
    cents = as_float_matrix(centroids, "centroids", dim=model.aggregator.num_channels).astype(np.float64)
    norms = maps.transpose(0, 1).flatten(1).norm(dim=0)                  # one per position of every map
    alpha = netvlad_alpha(cents, descs) / float(norms[norms > 0].mean()) / check_positive(temperature, "temperature")
    salad_scores_from_centroids(model.aggregator, cents, alpha)
    return np.asarray(centroids), alpha


def init_salad(model: "VPRModel", images, batch_size: int = 256) -> tuple[torch.Tensor, torch.Tensor]:
    """SALAD's data-dependent initialisation on a backbone whose local features share a large common part.

    Runs the backbone over ``images`` (uint8 ``(N, H, W, 3)``, e.g. the training database), takes the mean
    and the standard deviation (clamped at 1e-3) of each channel over every position of every image, and
    folds ``x -> (x - mean) / std`` into the first layer of SALAD's score and cluster-feature heads
    (:meth:`vpr_nb.aggregation.SALAD.standardise_inputs`; notebook 05 measures the collapse it removes).
    Returns ``(mean, std)``. Deterministic.
    """
    if not isinstance(getattr(model, "aggregator", None), SALAD):
        raise ValueError("init_salad needs a VPRModel whose aggregator is SALAD (build_model(..., 'salad'))")
    arr = as_image_array(images)
    if len(arr) == 0:
        raise ValueError("init_salad needs at least one image")
    batch_size = check_int(batch_size, "batch_size")
    with torch.no_grad():
        maps = torch.cat([model.backbone(images_to_tensor(arr[s:s + batch_size]))
                          for s in range(0, len(arr), batch_size)])
    x = maps.transpose(0, 1).flatten(1)                                      # [C, all positions]
    mean, std = x.mean(1), x.std(1).clamp_min(1e-3)
    model.aggregator.standardise_inputs(mean, std)
    return mean, std
