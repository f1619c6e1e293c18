"""The check every backbone and :class:`vpr_nb.models.VPRModel` apply to their input image batch."""
from __future__ import annotations

import torch

from .._checks import check_tensor


def _check_images(x, name: str, channels: int, *, multiple_of: int = 1, min_size: int = 1) -> torch.Tensor:
    """Validate a finite float image batch ``[B, channels, H, W]`` (B ≥ 1, H and W ≥ ``min_size``,
    multiples of ``multiple_of``)."""
    check_tensor(x, name, ndim=4)
    b, c, h, w = x.shape
    if c != channels:
        raise ValueError(f"{name} must have {channels} channels ([B, {channels}, H, W]), got shape {tuple(x.shape)}; "
                         f"convert uint8 NHWC images with vpr_nb.image_tensors.images_to_tensor")
    if b == 0:
        raise ValueError(f"{name} is an empty batch (shape {tuple(x.shape)}): it needs at least one image")
    if h < min_size or w < min_size:
        raise ValueError(f"{name} images must be at least {min_size}x{min_size} pixels for this backbone, "
                         f"got {h}x{w}; resize them")
    if h % multiple_of or w % multiple_of:
        raise ValueError(f"{name} height and width must be multiples of the patch size {multiple_of}, got {h}x{w}; "
                         f"resize or crop to e.g. {max(multiple_of, h - h % multiple_of)}x"
                         f"{max(multiple_of, w - w % multiple_of)}")
    return x
