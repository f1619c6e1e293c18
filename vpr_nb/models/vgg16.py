"""VGG16 up to conv5_3, the NetVLAD backbone, loading torchvision's ``vgg16-397923af.pth`` without torchvision."""
from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path

import torch
from torch import nn

from .image_checks import _check_images
from .weights import read_weights

VGG16_WEIGHTS_URL = "https://download.pytorch.org/models/vgg16-397923af.pth"

# torchvision's VGG16 configuration "D": conv output widths, "M" = 2×2 max-pool.
_VGG16_CFG = (64, 64, "M", 128, 128, "M", 256, 256, 256, "M", 512, 512, 512, "M", 512, 512, 512)
# Index in ``features`` of the first conv of each block, with torchvision's numbering.
_VGG16_BLOCK_START = {"conv1": 0, "conv2": 5, "conv3": 10, "conv4": 17, "conv5": 24}


def _vgg16_conv5_3_layers() -> nn.Sequential:
    """VGG16 ``features`` with torchvision's indices, ending at conv5_3 (index 28, before its ReLU)."""
    layers: list[nn.Module] = []
    cin = 3
    for v in _VGG16_CFG:
        if v == "M":
            layers.append(nn.MaxPool2d(2, 2))
        else:
            layers += [nn.Conv2d(cin, v, 3, padding=1), nn.ReLU(inplace=True)]
            cin = v
    return nn.Sequential(*layers[:-1])


def _read_state_dict(source) -> Mapping:
    """A state dict given directly, or read from a file with :func:`read_weights` (``weights_only=True``)."""
    if isinstance(source, Mapping):
        return source
    if not isinstance(source, (str, os.PathLike)):
        raise ValueError(f"pretrained_state_dict must be None, a path to a .pth file or a state dict, "
                         f"got {type(source).__name__}")
    path = Path(source)
    if not path.is_file():
        raise FileNotFoundError(
            f"VGG16 weights not found at {path}. Download torchvision's ImageNet VGG16 weights "
            f"{VGG16_WEIGHTS_URL} (file vgg16-397923af.pth, 528 MB) and pass its path.")
    return read_weights(path, "VGG16 weights file")


class VGG16Backbone(nn.Module):
    """VGG16 conv layers up to conv5_3, the backbone of NetVLAD (Arandjelović et al., CVPR 2016).

    ``features`` is an :class:`nn.Sequential` numbered as torchvision's ``vgg16().features``
    (convs at 0, 2, 5, 7, 10, 12, 14, 17, 19, 21, 24, 26, 28), so torchvision's state dict loads
    as is. As in the widely used Nanne/pytorch-NetVlad port, the last ReLU and max-pool are cut
    (``features[:-2]``): the output is conv5_3 before its ReLU, 512 channels at stride 16, and may be
    negative (NetVLAD L2-normalises each local feature; GeM clamps at ``eps``).

    ``pretrained_state_dict``: ``None`` (random init), a path to torchvision's ``vgg16-397923af.pth``
    or a state dict. Its ``features.*`` entries are loaded, ``classifier.*`` ignored, anything else is
    an error. ``trainable_from``: the first block that trains (``"conv1"`` … ``"conv5"``, or ``"none"``
    to freeze everything); earlier layers get ``requires_grad=False`` and run without autograd. The
    default ``"conv5"`` trains conv5_1–conv5_3 only, as NetVLAD does.
    """

    out_channels = 512
    stride = 16

    def __init__(self, pretrained_state_dict=None, trainable_from: str = "conv5") -> None:
        super().__init__()
        valid = (*_VGG16_BLOCK_START, "none")
        if trainable_from not in valid:
            raise ValueError(f"trainable_from must be one of {', '.join(valid)}, got {trainable_from!r}")
        self.features = _vgg16_conv5_3_layers()
        if pretrained_state_dict is not None:
            self._load(_read_state_dict(pretrained_state_dict))
        self.num_frozen = _VGG16_BLOCK_START.get(trainable_from, len(self.features))
        for layer in self.features[:self.num_frozen]:
            layer.requires_grad_(False)

    def _load(self, state: Mapping) -> None:
        """Load the ``features.*`` tensors of a torchvision VGG16 state dict, with clear errors."""
        other = sorted(k for k in state if not k.startswith(("features.", "classifier.")))
        if other:
            raise ValueError(f"not a torchvision VGG16 state dict: unexpected keys {other[:5]} "
                             f"(expected only features.* and classifier.*)")
        own = self.features.state_dict()
        given = {k[len("features."):]: v for k, v in state.items() if k.startswith("features.")}
        missing = sorted(set(own) - set(given), key=lambda k: int(k.split(".")[0]))
        extra = sorted(set(given) - set(own))
        if missing or extra:
            raise ValueError(f"state dict does not match VGG16 features: missing {missing[:5]}, unexpected "
                             f"{extra[:5]} (a vgg16_bn or vgg19 file? use torchvision's plain vgg16-397923af.pth)")
        for k, v in given.items():
            if not isinstance(v, torch.Tensor) or v.shape != own[k].shape:
                shape = tuple(v.shape) if isinstance(v, torch.Tensor) else type(v).__name__
                raise ValueError(f"features.{k} has shape {shape}, VGG16 needs {tuple(own[k].shape)}")
        self.features.load_state_dict(given)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """``x`` ``[B, 3, H, W]`` (H, W ≥ 16) → conv5_3 map ``[B, 512, H//16, W//16]``."""
        _check_images(x, "x", 3, min_size=self.stride)
        with torch.no_grad():
            x = self.features[:self.num_frozen](x)
        return self.features[self.num_frozen:](x)

