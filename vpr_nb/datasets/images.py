"""Reading dataset images from disk: Pillow decoding, antialiased resizing, ImageNet normalisation.

- :func:`read_image` one file -> float ``(3, H, W)`` tensor (normalised by
  :func:`vpr_nb.image_tensors.normalize_imagenet`, the package's one normalisation path);
- :class:`ImageDataset` a :class:`torch.utils.data.Dataset` of ``(image, index)`` for a DataLoader
  (pytorch-NetVlad's database-then-queries indexing), no torchvision needed;
- :class:`ImageArray` a lazy ``(N, H, W, 3)`` uint8 "array" that the training loop and
  :func:`vpr_nb.evaluation.compute_descriptors` index like the in-memory synthetic images;
- :func:`find_unreadable_images` the truncated / corrupt files of a dataset (draft-mode JPEG decoding).

Memory is bounded: an image of more than :data:`MAX_IMAGE_PIXELS` pixels (25 MP, width x height as its
header gives them, read before any pixel is decoded) is refused with a ValueError naming the file,
except a JPEG read with a ``size``, which is decoded at the 1/2, 1/4 or 1/8 scale (Pillow's ``draft``)
that still covers ``size``, if that fits the limit. A read costs about 20 bytes per decoded pixel
(Pillow's and numpy's bytes, then the float tensor), so at most about 0.5 GB; the largest images of
the supported datasets (Tokyo 24/7's 4032 x 3024) are 12 MP. Pillow's own decompression-bomb refusal
(above 179 MP) becomes the same ValueError. 16-bit grayscale PNGs (Pillow mode ``I;16``) are scaled
by 1/65535, not clipped to white.
"""
from __future__ import annotations

import os
from typing import Sequence

import numpy as np
import torch
import torch.nn.functional as F

from .._checks import check_int
from ..image_tensors import normalize_imagenet


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


MAX_IMAGE_PIXELS = 25_000_000      # width x height above which an image is not decoded (module docstring)
_SIXTEEN_BIT_MODES = ("I;16", "I;16L", "I;16B", "I;16N", "I")   # Pillow's modes of 16-bit grayscale PNGs


def _open(path):
    """``PIL.Image.open(path)`` (lazy: the header only); errors as FileNotFoundError / ValueError naming the file."""
    from PIL import Image, UnidentifiedImageError

    try:
        return Image.open(path)
    except FileNotFoundError:
        raise FileNotFoundError(f"image not found: {path}") from None
    except Image.DecompressionBombError as exc:
        raise ValueError(f"{path}: Pillow refuses to decode it as a possible decompression bomb ({exc}); vpr_nb "
                         f"reads images of at most MAX_IMAGE_PIXELS = {MAX_IMAGE_PIXELS} pixels: downscale the "
                         f"file or drop it from the dataset") from None
    except (UnidentifiedImageError, OSError) as exc:
        raise ValueError(f"cannot read image {path}: {exc}") from None


def _bounded(im, path, size) -> None:
    """Draft an over-large JPEG down towards ``size`` (H, W), then refuse an image still above MAX_IMAGE_PIXELS."""
    w, h = im.size
    if w * h > MAX_IMAGE_PIXELS and im.format == "JPEG" and size is not None:
        im.draft("RGB", (size[1], size[0]))          # the smallest DCT scale whose size still covers (W, H)
    if im.size[0] * im.size[1] > MAX_IMAGE_PIXELS:
        jpeg = " or read it with a size= (JPEGs are then decoded at 1/2 to 1/8 scale)" if im.format == "JPEG" else ""
        raise ValueError(f"{path}: {w}x{h} pixels ({w * h / 1e6:.1f} MP) is more than "
                         f"vpr_nb.datasets.images.MAX_IMAGE_PIXELS ({MAX_IMAGE_PIXELS / 1e6:g} MP), so it is not "
                         f"decoded (it would need about {w * h * 20 / 2 ** 30:.1f} GiB); downscale the file{jpeg}, "
                         f"or raise MAX_IMAGE_PIXELS if you have the memory")


def _pixels(im) -> torch.Tensor:
    """The decoded image as a float (3, H, W) tensor in [0, 1]: 16-bit grayscale / 65535, else RGB / 255."""
    if im.mode in _SIXTEEN_BIT_MODES:
        g = np.asarray(im).astype(np.float32)
        g = np.clip(g, 0.0, 65535.0, out=g) / np.float32(65535.0)
        return torch.from_numpy(g)[None].expand(3, -1, -1).contiguous()
    return torch.from_numpy(np.array(im.convert("RGB"), dtype=np.uint8)).permute(2, 0, 1).float().div_(255.0)


def read_image(path, size=None, normalize: bool = True) -> torch.Tensor:
    """Read one image with Pillow as a float (3, H, W) tensor.

    Pixels are scaled to [0, 1] (8-bit / 255, 16-bit grayscale / 65535), optionally resized to
    ``size`` = (H, W) with antialiased bilinear interpolation (``F.interpolate``), then normalised
    with the ImageNet statistics ``x' = (x - mean) / std`` (mean = (0.485, 0.456, 0.406),
    std = (0.229, 0.224, 0.225)) by :func:`vpr_nb.image_tensors.normalize_imagenet`, the same path as the
    in-memory images take. Images above :data:`MAX_IMAGE_PIXELS` are refused before decoding (a JPEG
    read with ``size`` is first decoded at a reduced scale); errors name the file.
    """
    size = _as_size(size)
    with _open(path) as im:
        _bounded(im, path, size)
        try:
            x = _pixels(im)
        except (OSError, ValueError, SyntaxError) as exc:   # what Pillow's decoders raise on bad data
            raise ValueError(f"cannot read image {path}: {exc}") from None
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
    try:
        with _open(path) as im:
            if im.format == "JPEG":      # decode at 1/8 scale: every byte is still read, so truncation shows
                im.draft("RGB", (max(1, im.width // 8), max(1, im.height // 8)))
            _bounded(im, path, None)     # too large to read is unusable too (and is not decoded here either)
            im.load()
    except Exception as exc:  # noqa: BLE001 - any decoder error makes the file unusable
        return f"{type(exc).__name__}: {exc}"
    return None


def find_unreadable_images(paths: Sequence, num_workers: int = 4) -> list[tuple[str, str]]:
    """``(path, error)`` of every image in ``paths`` that Pillow cannot fully decode (truncated or corrupt
    files, missing files) or that is too large to read (:data:`MAX_IMAGE_PIXELS`), in the order given.
    JPEGs are decoded in draft mode (1/8 scale), which still reads the whole stream, so this costs a
    fraction of a full read."""
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


__all__ = ["read_image", "ImageDataset", "ImageArray", "find_unreadable_images", "MAX_IMAGE_PIXELS"]
