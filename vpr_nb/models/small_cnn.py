"""SmallCNN: the course's 4-layer CPU backbone (total stride 4), the architecture of the course backbone.

It trains at >1000 images/s on a 2-core CPU on the course's 32×48 synthetic images; the notebooks' default.
"""
from __future__ import annotations

import math

import torch
from torch import nn

from .._checks import check_int
from ..pointwise import PointwiseConv2d
from .image_checks import _check_images


def _conv_gn_relu(cin: int, cout: int, kernel: int, stride: int, groups: int) -> list[nn.Module]:
    """Conv (no bias, the norm has one) → GroupNorm with gcd(groups, cout) groups → ReLU."""
    padding = 0 if kernel == stride else kernel // 2
    return [nn.Conv2d(cin, cout, kernel, stride, padding, bias=False),
            nn.GroupNorm(math.gcd(groups, cout), cout), nn.ReLU(inplace=True)]


class SmallCNN(nn.Module):
    """A small CPU backbone with total stride 4: 32×48 images → 8×12 = 96 local features.

    Layers: a 4×4 stride-4 "patchify" conv (the convolutional twin of a ViT patch embedding) to
    ``width`` channels, two 3×3 convs (``width`` → ``width`` → ``2·width``) and a 1×1 projection to
    ``out_channels``; each followed by ReLU, the first three by GroupNorm (and the projection too with
    ``final_norm`` groups > 0: each image's local features are centred and scaled per group of channels
    before the last ReLU, so a component every position shares cannot dominate them; tried for the course
    backbone and not kept, see :mod:`vpr_nb.pretrain`). The output map is non-negative, as GeM (Eq. (1) of
    Radenović et al., TPAMI 2018) assumes.

    GroupNorm rather than BatchNorm: VPR batches hold a few places × a few views each, so batch
    statistics are strongly correlated and small; GroupNorm normalises each image on its own, trains
    the same at any batch size and behaves identically in ``train()`` and ``eval()`` (no running
    statistics), so descriptors computed during training and at test time agree.

    For SALAD the number of local features n = h·w (96 for 32×48 inputs) must exceed the number of
    clusters m, or the optimal transport has more clusters than features to fill them.

    ``forward_with_token`` also returns a global token ``Linear(mean over positions of the map)``,
    the analogue of DINOv2's CLS token that SALAD's global branch consumes.
    """

    stride = 4

    def __init__(self, in_channels: int = 3, width: int = 32, out_channels: int = 128, norm_groups: int = 8,
                 final_norm: int = 0) -> None:
        super().__init__()
        self.in_channels = check_int(in_channels, "in_channels")
        width = check_int(width, "width")
        self.out_channels = check_int(out_channels, "out_channels")
        groups = check_int(norm_groups, "norm_groups")
        self.final_norm = check_int(final_norm, "final_norm", minimum=0)
        if self.final_norm and self.out_channels % self.final_norm:
            raise ValueError(f"final_norm={final_norm} groups must divide out_channels={out_channels}")
        layers = [*_conv_gn_relu(self.in_channels, width, 4, 4, groups),      # built in this order: the same
                  *_conv_gn_relu(width, width, 3, 1, groups),                 # seed gives the same weights
                  *_conv_gn_relu(width, 2 * width, 3, 1, groups),
                  PointwiseConv2d(2 * width, self.out_channels, 1)]
        if self.final_norm:      # GroupNorm on the projection too: each image's local features centred per group
            layers.append(nn.GroupNorm(self.final_norm, self.out_channels))
        self.features = nn.Sequential(*layers, nn.ReLU(inplace=True))
        self.token = nn.Linear(self.out_channels, self.out_channels)
        self.num_frozen = 0                       # leading layers of ``features`` that run without autograd
        self.frozen_cache = None                  # a vpr_nb.feature_cache.FrozenFeatureCache for those layers

    # first layer of each block in ``features``: patchify, conv, conv, 1x1 projection
    BLOCK_STARTS = (0, 3, 6, 9)

    def set_trainable_blocks(self, k: int) -> "SmallCNN":
        """Train only the last ``k`` of the 4 blocks (0: all frozen, 4: all train); earlier layers get
        ``requires_grad=False`` and run under ``torch.no_grad()``, through ``frozen_cache`` when one is
        attached (:mod:`vpr_nb.feature_cache`: each image's frozen map computed once). The global token
        layer always trains."""
        k = check_int(k, "trainable_blocks", minimum=0, maximum=len(self.BLOCK_STARTS))
        self.num_frozen = len(self.features) if k == 0 else self.BLOCK_STARTS[len(self.BLOCK_STARTS) - k]
        for i, layer in enumerate(self.features):
            layer.requires_grad_(i >= self.num_frozen)
        return self

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """``x`` ``[B, in_channels, H, W]`` (H, W ≥ 4) → feature map ``[B, out_channels, H//4, W//4]``."""
        _check_images(x, "x", self.in_channels, min_size=self.stride)
        if self.num_frozen:
            frozen, cache = self.features[:self.num_frozen], getattr(self, "frozen_cache", None)
            with torch.no_grad():
                x = frozen(x) if cache is None else cache(frozen, x)
        return self.features[self.num_frozen:](x)

    def forward_with_token(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``x`` → (feature map ``[B, C, h, w]``, token ``[B, C]`` = Linear(spatial mean of the map))."""
        fmap = self.forward(x)
        return fmap, self.token(fmap.mean(dim=(2, 3)))
