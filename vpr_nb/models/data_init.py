"""The data-driven initialisations of the aggregator heads: NetVLAD's k-means and SALAD's standardised inputs."""
from __future__ import annotations

import numpy as np
import torch

from .._checks import check_int
from ..aggregation import SALAD, NetVLAD, kmeans_centroids, sample_local_descriptors
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
    arr = as_image_array(images)
    if max_images is not None and len(arr) > check_int(max_images, "max_images"):
        arr = arr[np.sort(np.random.default_rng(seed).choice(len(arr), max_images, replace=False))]
    maps = []
    with torch.no_grad():
        for start in range(0, len(arr), batch_size):
            maps.append(model.backbone(images_to_tensor(arr[start:start + batch_size])))
    descs = sample_local_descriptors(torch.cat(maps), per_image, seed=seed, skip_zero=True)
    cents = kmeans_centroids(descs, model.aggregator.num_clusters, niter=niter, seed=seed)
    model.aggregator.init_from_clusters(cents, descs)
    return descs, cents


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
