"""The VPR model, backbone + aggregator, and :func:`build_model`, which builds one by backbone and aggregator name."""
from __future__ import annotations

from collections.abc import Mapping

import torch
import torch.nn.functional as F
from torch import nn

from .._checks import validated_inputs
from ..aggregation import make_aggregator
from .dinov2 import load_dinov2
from .image_checks import _check_images
from .small_cnn import SmallCNN
from .vgg16 import VGG16Backbone

BACKBONE_NAMES = ("small_cnn", "vgg16", "dinov2")   # the keys of BACKBONES


class VPRModel(nn.Module):
    """``backbone`` (image → local features) followed by ``aggregator`` (→ global descriptor).

    Aggregators with ``needs_token = True`` (SALAD) receive ``backbone.forward_with_token(x)``, the
    pair (feature map, global token); the others receive ``backbone(x)``. ``forward`` returns
    L2-normalised ``[B, out_dim]`` descriptors, so inner product = cosine similarity.
    """

    def __init__(self, backbone: nn.Module, aggregator: nn.Module) -> None:
        super().__init__()
        if not isinstance(backbone, nn.Module) or not isinstance(aggregator, nn.Module):
            raise ValueError(f"backbone and aggregator must be torch.nn.Module instances, got "
                             f"{type(backbone).__name__} and {type(aggregator).__name__}")
        out_dim = getattr(aggregator, "out_dim", None)
        if isinstance(out_dim, bool) or not isinstance(out_dim, int) or out_dim < 1:
            raise ValueError(f"aggregator {type(aggregator).__name__} must have a positive integer out_dim, "
                             f"got {out_dim!r}; build it with in_channels set")
        self.needs_token = bool(getattr(aggregator, "needs_token", False))
        if self.needs_token and not hasattr(backbone, "forward_with_token"):
            raise ValueError(f"{type(aggregator).__name__} needs a global token but {type(backbone).__name__} "
                             f"has no forward_with_token; use SmallCNN or DINOv2Backbone")
        self.backbone = backbone
        self.aggregator = aggregator
        self.out_dim = out_dim

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """``x`` float ``[B, 3, H, W]`` (ImageNet-normalised) → L2-normalised descriptors ``[B, out_dim]``.

        A backbone with an ``in_channels`` attribute (e.g. ``SmallCNN(in_channels=1)``) sets the
        expected channel count instead of 3.
        """
        _check_images(x, "x", getattr(self.backbone, "in_channels", 3))
        with validated_inputs():    # the backbone and the aggregator do not scan x's values again
            features = self.backbone.forward_with_token(x) if self.needs_token else self.backbone(x)
            return F.normalize(self.aggregator(features), p=2, dim=1)


# the one map from a backbone name to what builds it (build_model; the config checks backbone_kwargs
# against these signatures): a new backbone is a class or function and a line here
BACKBONES = {"small_cnn": SmallCNN, "vgg16": VGG16Backbone, "dinov2": load_dinov2}
assert tuple(BACKBONES) == BACKBONE_NAMES


def build_model(backbone: str | nn.Module = "small_cnn", aggregator: str = "gem", *,
                backbone_kwargs: Mapping | None = None, **aggregator_kwargs) -> VPRModel:
    """Build a :class:`VPRModel` by name.

    ``backbone``: ``"small_cnn"`` (:class:`SmallCNN`), ``"vgg16"`` (:class:`VGG16Backbone`),
    ``"dinov2"`` (:func:`load_dinov2`), or an already built backbone module with ``out_channels``;
    ``backbone_kwargs`` go to its constructor. ``aggregator`` and ``aggregator_kwargs`` go to
    :func:`vpr_nb.aggregation.make_aggregator` with ``in_channels = backbone.out_channels``, e.g.
    ``build_model("small_cnn", "netvlad", num_clusters=16)`` or
    ``build_model("vgg16", "gem", backbone_kwargs={"pretrained_state_dict": "vgg16-397923af.pth"})``.
    """
    if backbone_kwargs is not None and not isinstance(backbone_kwargs, Mapping):
        raise ValueError(f"backbone_kwargs must be a dict or None, got {type(backbone_kwargs).__name__}")
    if isinstance(backbone, str):
        if backbone not in BACKBONES:
            raise ValueError(f"unknown backbone {backbone!r}; valid names are {', '.join(BACKBONE_NAMES)} "
                             f"(or pass a backbone module)")
        backbone = BACKBONES[backbone](**(backbone_kwargs or {}))
    elif not isinstance(backbone, nn.Module) or not hasattr(backbone, "out_channels"):
        raise ValueError(f"backbone must be one of {', '.join(BACKBONE_NAMES)} or a module with out_channels, "
                         f"got {type(backbone).__name__}")
    elif backbone_kwargs:
        raise ValueError("backbone_kwargs only apply when backbone is given by name")
    return VPRModel(backbone, make_aggregator(aggregator, backbone.out_channels, **aggregator_kwargs))
