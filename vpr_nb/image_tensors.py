"""Images as tensors: uint8 ``(N, H, W, 3)`` images to the normalised float tensors every model reads.

The one normalisation path of the package (ImageNet statistics, as torchvision's pretrained backbones and the
papers' code use): :func:`images_to_tensor` for in-memory images and :func:`vpr_nb.datasets.read_image` for
files both end in :func:`normalize_imagenet`.
"""
from __future__ import annotations

import numpy as np
import torch

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)


def normalize_imagenet(x: torch.Tensor) -> torch.Tensor:
    """``(x - mean) / std`` per channel with the ImageNet statistics (:data:`IMAGENET_MEAN`,
    :data:`IMAGENET_STD`), for float images in [0, 1] with channels at dim -3 (``(3, H, W)`` or
    ``(N, 3, H, W)``). The one normalisation path of the package: :func:`images_to_tensor` and
    :func:`vpr_nb.datasets.read_image` both end here."""
    if not isinstance(x, torch.Tensor) or not x.is_floating_point() or x.ndim < 3 or x.shape[-3] != 3:
        got = f"{x.dtype} of shape {tuple(x.shape)}" if isinstance(x, torch.Tensor) else type(x).__name__
        raise ValueError(f"normalize_imagenet needs a float tensor with 3 channels at dim -3, got {got}; "
                         f"scale uint8 images to [0, 1] first (images_to_tensor does both)")
    return (x - torch.tensor(IMAGENET_MEAN).view(3, 1, 1)) / torch.tensor(IMAGENET_STD).view(3, 1, 1)


def images_to_tensor(images) -> torch.Tensor:
    """uint8 images (N, H, W, 3) -> float tensor (N, 3, H, W), scaled to [0, 1] then ImageNet-normalised."""
    if isinstance(images, torch.Tensor):
        images = images.numpy()
    arr = np.asarray(images)
    if arr.ndim != 4 or arr.shape[-1] != 3:
        raise ValueError(f"images must be (N, H, W, 3) uint8, got shape {arr.shape}")
    if arr.dtype != np.uint8:
        raise ValueError(f"images must be uint8 in [0, 255], got dtype {arr.dtype}")
    x = torch.from_numpy(np.ascontiguousarray(arr)).permute(0, 3, 1, 2).float().div_(255.0)
    return normalize_imagenet(x)


def as_image_array(images):
    """``images`` as an indexable ``(N, H, W, 3)`` uint8 array: numpy arrays (and lists) as numpy,
    lazy on-disk arrays (:class:`vpr_nb.datasets.ImageArray`, anything with ``shape``, ``dtype``
    and ``__getitem__``) as they are, so that only the indexed images are read."""
    if isinstance(images, np.ndarray):
        return images
    if hasattr(images, "shape") and hasattr(images, "__getitem__") and hasattr(images, "dtype"):
        return images
    return np.asarray(images)
