"""Backbones and the VPR model wrapper: image ``[B, 3, H, W]`` → local feature map → global descriptor.

========================================  ===================================================================
:mod:`~vpr_nb.models.small_cnn`           :class:`SmallCNN`: a 4-layer CNN (total stride 4) that trains at
                                          >1000 images/s on a 2-core CPU on the course's 32×48 synthetic
                                          images; the notebooks' default and the course backbone's architecture
:mod:`~vpr_nb.models.vgg16`               :class:`VGG16Backbone`: VGG16 up to conv5_3, the NetVLAD backbone
                                          (Arandjelović et al., CVPR 2016), loading torchvision's
                                          ``vgg16-397923af.pth`` without importing torchvision
:mod:`~vpr_nb.models.dinov2`              :class:`DINOv2Backbone` and :func:`load_dinov2`: the DINOv2 ViT-B/14
                                          of DINOv2-SALAD (Izquierdo & Civera, CVPR 2024), from a local clone
                                          of ``facebookresearch/dinov2`` (never downloads)
:mod:`~vpr_nb.models.vpr_model`           :class:`VPRModel` and :func:`build_model`: backbone + aggregator
                                          (:mod:`vpr_nb.aggregation`); :data:`BACKBONES`, the name → builder map
:mod:`~vpr_nb.models.data_init`           :func:`init_netvlad` (k-means), :func:`init_salad` (standardised
                                          head inputs) and :func:`init_salad_scores_from_kmeans` (SALAD's
                                          scores from k-means): the heads' initialisations from training images
:mod:`~vpr_nb.models.weights`             :func:`read_weights` (weights-only reads, one-line errors) and
                                          :func:`load_state_checked` (a state dict that must fit exactly)
:mod:`~vpr_nb.models.image_checks`        the input check every backbone and :class:`VPRModel` apply
========================================  ===================================================================

Every backbone has ``out_channels`` (C) and ``stride``, and ``forward(x)`` returns the feature map
``[B, C, H/stride, W/stride]``. Backbones with a global token (SmallCNN, DINOv2) also have
``forward_with_token(x) -> (feature map, token [B, C])``, which aggregators that set
``needs_token = True`` (SALAD) receive.

Images are float ``[B, 3, H, W]`` tensors, ImageNet-normalised as
:func:`vpr_nb.image_tensors.images_to_tensor` makes them.
"""
from __future__ import annotations

from .data_init import init_netvlad, init_salad, init_salad_scores_from_kmeans, salad_scores_from_centroids
from .dinov2 import DINOV2_HUB_ENV, DINOV2_MODELS, DINOv2Backbone, load_dinov2
from .small_cnn import SmallCNN
from .vgg16 import VGG16_WEIGHTS_URL, VGG16Backbone
from .vpr_model import BACKBONE_NAMES, BACKBONES, VPRModel, build_model
from .weights import load_state_checked, read_weights

__all__ = ["BACKBONE_NAMES", "BACKBONES", "DINOV2_HUB_ENV", "DINOV2_MODELS", "DINOv2Backbone", "SmallCNN",
           "VGG16Backbone", "VGG16_WEIGHTS_URL", "VPRModel", "build_model", "init_netvlad", "init_salad",
           "init_salad_scores_from_kmeans", "salad_scores_from_centroids", "load_dinov2", "load_state_checked", "read_weights"]
