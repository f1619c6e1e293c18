"""Reading dataset images from disk: Pillow decoding, antialiased resizing, ImageNet normalisation.

- :func:`read_image` one file -> float ``(3, H, W)`` tensor (normalised by
  :func:`vpr_nb.evaluation.normalize_imagenet`, the package's one normalisation path);
- :class:`ImageDataset` a :class:`torch.utils.data.Dataset` of ``(image, index)`` for a DataLoader
  (pytorch-NetVlad's database-then-queries indexing), no torchvision needed;
- :class:`ImageArray` a lazy ``(N, H, W, 3)`` uint8 "array" that the training loop and
  :func:`vpr_nb.evaluation.compute_descriptors` index like the in-memory synthetic images;
- :func:`find_unreadable_images` the truncated / corrupt files of a dataset (draft-mode JPEG decoding).
"""
from __future__ import annotations

import os
from typing import Sequence

import numpy as np
import torch
import torch.nn.functional as F

from .._checks import check_int
from ..evaluation import normalize_imagenet


def _as_size(size) -> tuple[int, int] | None:
    """``None``, an int ``s`` (-> (s, s)) or ``(height, width)`` as a checked ``(H, W)`` tuple."""
    if size is None:
        return None
    if isinstance(size, (int, np.integer)) and not isinstance(size, bool):
        size = (int(size), int(size))
    try:
        h, w = (int(s) for s in size)
    except (TypeError, ValueError):
        raise ValueError(f"size must be None, an int or (height, width), got {size!r}") from None
    if h < 1 or w < 1:
        raise ValueError(f"size must be positive, got {(h, w)}")
    return h, w


def read_image(path, size=None, normalize: bool = True) -> torch.Tensor:
    """Read one image with Pillow as a float (3, H, W) tensor.

    Pixels are scaled to [0, 1], optionally resized to ``size`` = (H, W) with antialiased bilinear
    interpolation (``F.interpolate``), then normalised with the ImageNet statistics
    ``x' = (x - mean) / std`` (mean = (0.485, 0.456, 0.406), std = (0.229, 0.224, 0.225)) by
    :func:`vpr_nb.evaluation.normalize_imagenet`, the same path as the in-memory images take.
    """
    from PIL import Image, UnidentifiedImageError

    size = _as_size(size)
    try:
        with Image.open(path) as im:
            arr = np.asarray(im.convert("RGB"), dtype=np.uint8)
    except FileNotFoundError:
        raise FileNotFoundError(f"image not found: {path}") from None
    except (UnidentifiedImageError, OSError) as exc:
        raise ValueError(f"cannot read image {path}: {exc}") from None
    x = torch.from_numpy(arr.copy()).permute(2, 0, 1).float().div_(255.0)
    if size is not None and tuple(x.shape[1:]) != size:
        x = F.interpolate(x[None], size=size, mode="bilinear", align_corners=False, antialias=True)[0]
    if normalize:
        x = normalize_imagenet(x)
    return x


class ImageDataset(torch.utils.data.Dataset):
    """A torch Dataset of image files: item ``i`` is ``(image (3, H, W) float tensor, i)``.

    Reading with Pillow, resizing and normalisation as :func:`read_image`. Without ``size`` images
    keep their native resolution (pytorch-NetVlad feeds Pittsburgh at 640x480), so batch them only if
    they share one size.
    """

    def __init__(self, paths: Sequence, size=None, normalize: bool = True):
        if isinstance(paths, (str, os.PathLike)):
            raise ValueError("paths must be a sequence of image paths, not a single path")
        self.paths = [str(p) for p in paths]
        if not self.paths:
            raise ValueError("paths is empty: an ImageDataset needs at least one image")
        self.size = _as_size(size)
        self.normalize = bool(normalize)

    def __len__(self) -> int:
        return len(self.paths)

    def __getitem__(self, index: int):
        if not -len(self.paths) <= index < len(self.paths):
            raise IndexError(f"index {index} out of range for {len(self.paths)} images")
        return read_image(self.paths[index], self.size, self.normalize), int(index) % len(self.paths)


class ImageArray:
    """A lazy ``(N, H, W, 3)`` uint8 "array" of image files: indexing reads and resizes only the
    requested images (Pillow + antialiased ``F.interpolate``), so the training loop and
    :func:`vpr_nb.evaluation.compute_descriptors` can treat on-disk datasets like in-memory ones."""

    dtype = np.dtype(np.uint8)
    ndim = 4

    def __init__(self, paths: Sequence, size):
        self.paths = [str(p) for p in paths]
        if not self.paths:
            raise ValueError("ImageArray needs at least one image path")
        size = _as_size(size)
        if size is None:
            raise ValueError("ImageArray needs a fixed size (H, W) so that batches stack")
        self.size = size

    @property
    def shape(self) -> tuple[int, int, int, int]:
        return (len(self.paths), *self.size, 3)

    def __len__(self) -> int:
        return len(self.paths)

    def __getitem__(self, index) -> np.ndarray:
        idx = np.arange(len(self.paths))[index]
        if np.ndim(idx) == 0:
            return self[[int(idx)]][0]
        out = np.empty((len(idx), *self.size, 3), np.uint8)
        for k, i in enumerate(idx):
            x = read_image(self.paths[i], self.size, normalize=False)
            out[k] = (x.permute(1, 2, 0).clamp_(0, 1) * 255).round_().to(torch.uint8).numpy()
        return out


def _decode_error(path: str) -> str | None:
    from PIL import Image

    try:
        with Image.open(path) as im:
            if im.format == "JPEG":      # decode at 1/8 scale: every byte is still read, so truncation shows
                im.draft("RGB", (max(1, im.width // 8), max(1, im.height // 8)))
            im.load()
    except Exception as exc:  # noqa: BLE001 - any decoder error makes the file unusable
        return f"{type(exc).__name__}: {exc}"
    return None


def find_unreadable_images(paths: Sequence, num_workers: int = 4) -> list[tuple[str, str]]:
    """``(path, error)`` of every image in ``paths`` that Pillow cannot fully decode (truncated or corrupt
    files, missing files), in the order given. JPEGs are decoded in draft mode (1/8 scale), which still
    reads the whole stream, so this costs a fraction of a full read."""
    if isinstance(paths, (str, os.PathLike)):
        raise ValueError("paths must be a sequence of image paths, not a single path")
    num_workers = check_int(num_workers, "num_workers")
    paths = [str(p) for p in paths]
    if num_workers == 1 or len(paths) < 64:
        errors = [_decode_error(p) for p in paths]
    else:
        from concurrent.futures import ThreadPoolExecutor
        with ThreadPoolExecutor(num_workers) as pool:
            errors = list(pool.map(_decode_error, paths, chunksize=256))
    return [(p, e) for p, e in zip(paths, errors) if e is not None]


__all__ = ["read_image", "ImageDataset", "ImageArray", "find_unreadable_images"]
