"""Frozen blocks computed once: a per-image memo of a backbone's frozen layers.

When only the last block of the course backbone trains (``course_backbone(trainable_blocks=1)``), the first
three blocks give every image the same feature map at every step, every mining pass and every validation:
a fine-tune recomputes them thousands of times. :class:`FrozenFeatureCache` stores that map once per image
and hands it back on every later call, so an epoch runs only the trainable block and the head.

The cache sits where :class:`vpr_nb.models.SmallCNN` runs its frozen layers (``backbone.frozen_cache``), so
every caller benefits without change: the batch sources' training steps, the descriptor passes of triplet
mining, :func:`vpr_nb.evaluation.compute_descriptors` and the validation of :func:`vpr_nb.training.train`.

**Keys.** An image is recognised by its content: the exact float bytes the backbone receives, with their shape
and dtype. Keys are compared in full (a dict lookup hashes them and compares the bytes on a hash match), so
two different images can never share a stored map. The same image gives the same tensor
(``images_to_tensor`` is deterministic), so it hits; any other input (an augmented crop, another world)
misses and is computed as without the cache. Nothing about the data sources has to be declared.

**When a cache would be wrong, it is refused.** A memo is exact only if the frozen layers are a fixed,
deterministic function of one image: :func:`check_cacheable` accepts only layer types that have no random
behaviour and no train-mode statistics (convolutions, linear layers, GroupNorm / LayerNorm / InstanceNorm
without running statistics, ReLU-type activations, pooling, Identity) and refuses BatchNorm (batch statistics
in ``train()``), Dropout and any unknown module. The frozen weights are fingerprinted: if they change
(``load_state_dict`` with other values, a different number of frozen blocks) the stored maps are dropped.

**Memory.** ``float32`` storage by default: a course-backbone map (width 48: 96 channels × 8 × 12 for a
32×48 image) takes 36 KiB and its key (the 3 × 32 × 48 input floats) 18 KiB, so the tiny city's train + val
splits (1,599 images) take 84.3 MiB and the tiny route's (1,434 images) 75.6 MiB. ``float16`` storage halves
the maps but changes descriptors by about 1e-4 (measured in ``bench/bench_frozen_cache.py``), more than the
1e-5 the cached path must stay within, so it is only an option. Beyond ``max_bytes`` (maps and keys) new maps
are computed and not stored (counted in ``bypassed``). Maps are stored channels-last (``[h, w, C]``), the
layout the course's images give them, so a batch of hits is handed back without a copy. In use::

    cache = FrozenFeatureCache()
    with cache.attached(model.backbone):
        history = train(model, source, val_split, config)
"""
from __future__ import annotations

import contextlib
import hashlib

import numpy as np
import torch
from torch import nn

from ._checks import check_int
from .models import SmallCNN

# layer types whose output is a fixed function of one input, identical in train() and eval() mode
_DETERMINISTIC = (nn.Conv1d, nn.Conv2d, nn.Conv3d, nn.Linear, nn.GroupNorm, nn.LayerNorm, nn.ReLU, nn.ReLU6,
                  nn.LeakyReLU, nn.GELU, nn.SiLU, nn.Tanh, nn.Sigmoid, nn.Identity, nn.MaxPool2d, nn.AvgPool2d,
                  nn.AdaptiveAvgPool2d, nn.Flatten)
_CONTAINERS = (nn.Sequential, nn.ModuleList)
CACHE_DTYPES = {"float32": torch.float32, "float16": torch.float16}


def check_cacheable(frozen: nn.Module) -> None:
    """Raise ``ValueError`` unless every layer of ``frozen`` is deterministic and mode-independent.

    Refused: BatchNorm (``train()`` normalises with the batch's statistics, so an image's map depends on the
    batch it is in), Dropout of any kind (random), InstanceNorm with running statistics, and any layer type
    not known to be safe (a cache could silently freeze its randomness)."""
    if not isinstance(frozen, nn.Module):
        raise ValueError(f"frozen must be a torch.nn.Module, got {type(frozen).__name__}")
    for name, layer in frozen.named_modules():
        if isinstance(layer, _CONTAINERS):
            continue
        where = f"layer {name!r} ({type(layer).__name__})"
        if isinstance(layer, nn.modules.batchnorm._BatchNorm):
            raise ValueError(f"cannot cache the frozen blocks: {where} normalises with batch statistics in train "
                             f"mode, so an image's features depend on its batch; use GroupNorm or no cache")
        if isinstance(layer, nn.modules.dropout._DropoutNd):
            raise ValueError(f"cannot cache the frozen blocks: {where} is random in train mode; move the dropout "
                             f"after the frozen blocks or use no cache")
        if isinstance(layer, nn.modules.instancenorm._InstanceNorm):
            if layer.track_running_stats:
                raise ValueError(f"cannot cache the frozen blocks: {where} tracks running statistics")
            continue
        if not isinstance(layer, _DETERMINISTIC):
            raise ValueError(f"cannot cache the frozen blocks: {where} is not a layer known to be deterministic "
                             f"and mode-independent (known: {', '.join(t.__name__ for t in _DETERMINISTIC)})")


def image_keys(x: torch.Tensor) -> list[bytes]:
    """One key per image of ``x`` ``[B, ...]``: its exact float bytes (compare them with the input's
    :func:`input_signature`: the same bytes in another shape or dtype are another input)."""
    arr = np.ascontiguousarray(x.detach().cpu().numpy())
    return [row.tobytes() for row in arr.reshape(len(arr), -1)]


def input_signature(x: torch.Tensor) -> tuple:
    """The shape of one image of ``x`` and its dtype: keys are looked up among those of this signature."""
    return tuple(x.shape[1:]), str(x.dtype)


def _memory_format(x: torch.Tensor) -> torch.memory_format:
    """channels_last when ``x`` is stored so (``images_to_tensor`` permutes NHWC images), else contiguous: a
    convolution keeps its input's layout, and so must the cached maps, since a dropout after them draws its
    mask in memory order (the same seed would otherwise drop other positions)."""
    if x.dim() == 4 and not x.is_contiguous() and x.is_contiguous(memory_format=torch.channels_last):
        return torch.channels_last
    return torch.contiguous_format


def _weights_fingerprint(frozen: nn.Module) -> bytes:
    h = hashlib.sha1(usedforsecurity=False)
    for name, t in list(frozen.named_parameters()) + list(frozen.named_buffers()):
        t = t.detach().cpu().contiguous()
        h.update(f"{name}|{t.dtype}|{tuple(t.shape)}|".encode())
        h.update(t.view(torch.uint8).numpy().tobytes() if t.numel() else b"")
    h.update(repr([type(m).__name__ for m in frozen.modules()]).encode())
    return h.digest()


class FrozenFeatureCache:
    """Per-image memo of a backbone's frozen layers (see the module docstring).

    Args:
        dtype: storage precision, ``"float32"`` (exact) or ``"float16"`` (maps in half the memory, ~1e-4 error).
        max_bytes: stop storing new maps beyond this size (they are then computed on every call).

    Counters: ``hits`` and ``misses`` (images), ``bypassed`` (misses not stored because the cache was full),
    ``resets`` (times the frozen weights changed and the stored maps were dropped); ``nbytes``, ``len()``.
    """

    def __init__(self, dtype: str = "float32", max_bytes: int = 512 * 2 ** 20) -> None:
        if dtype not in CACHE_DTYPES:
            raise ValueError(f"dtype must be one of {sorted(CACHE_DTYPES)}, got {dtype!r}")
        self.dtype = CACHE_DTYPES[dtype]
        self.max_bytes = check_int(max_bytes, "max_bytes", minimum=0)
        self._rows: dict[tuple, dict[bytes, int]] = {}   # input signature -> {image key: row of _maps}
        self._maps: list[torch.Tensor] = []         # one [h, w, C] map per stored image, on the CPU
        self._key_bytes = 0
        self._fingerprint: bytes | None = None
        self._versions: tuple | None = None
        self.hits = self.misses = self.bypassed = self.resets = 0

    def __len__(self) -> int:
        return len(self._maps)

    @property
    def nbytes(self) -> int:
        """Bytes held by the stored maps and their keys."""
        return sum(m.numel() * m.element_size() for m in self._maps[:1]) * len(self._maps) + self._key_bytes

    def stats(self) -> dict:
        return {"images": len(self._maps), "MiB": round(self.nbytes / 2 ** 20, 2), "hits": self.hits,
                "misses": self.misses, "bypassed": self.bypassed, "resets": self.resets}

    def clear(self) -> None:
        self._rows, self._maps, self._key_bytes = {}, [], 0

    def _sync(self, frozen: nn.Module) -> None:
        """Drop the stored maps if the frozen layers or their weights changed since they were computed."""
        tensors = list(frozen.parameters()) + list(frozen.buffers())
        layers = list(frozen.modules())[1:]      # not the container: SmallCNN slices a new one on every call
        versions = tuple((t._version, t.data_ptr()) for t in tensors) + tuple(id(m) for m in layers)
        if versions == self._versions:
            return
        check_cacheable(frozen)
        fingerprint = _weights_fingerprint(frozen)
        if self._fingerprint is not None and fingerprint != self._fingerprint:
            self.clear()
            self.resets += 1
        self._fingerprint, self._versions = fingerprint, versions

    def _append(self, maps: torch.Tensor, key_bytes: int) -> list[int] | None:
        """Store ``maps`` ``[k, C, h, w]`` (one per image, no spare rows) as ``[h, w, C]`` copies; returns their
        row indices, or None when they and their keys (``key_bytes`` each) do not fit in ``max_bytes``."""
        nhwc = maps.detach().permute(0, 2, 3, 1)
        each = nhwc[0].numel() * self.dtype.itemsize
        if self._maps and self._maps[0].shape != nhwc.shape[1:]:
            h, w, c = self._maps[0].shape
            raise ValueError(f"the frozen blocks gave maps of shape {tuple(maps.shape[1:])}, the cache holds "
                             f"{(c, h, w)}: use one cache per image size")
        if self.nbytes + len(maps) * (each + key_bytes) > self.max_bytes:
            return None
        stored = torch.empty(nhwc.shape, dtype=self.dtype)
        stored.copy_(nhwc)                       # a copy: the caller's maps go on into the trainable layers
        first = len(self._maps)
        self._maps.extend(stored.unbind(0))
        self._key_bytes += len(maps) * key_bytes
        return list(range(first, len(self._maps)))

    def _gather(self, rows: list[int]) -> torch.Tensor:
        """The stored maps of ``rows`` as one ``[B, C, h, w]`` tensor in channels-last memory (a view)."""
        return torch.stack([self._maps[r] for r in rows]).permute(0, 3, 1, 2)

    def _remember(self, table: dict[bytes, int], keys: list[bytes], maps: torch.Tensor) -> None:
        first: dict[bytes, int] = {}
        for j, k in enumerate(keys):             # a batch may hold one image twice: store it once
            first.setdefault(k, j)
        rows = self._append(maps[list(first.values())], len(keys[0]))
        if rows is None:
            self.bypassed += len(keys)
            return
        table.update(zip(first, rows))

    def __call__(self, frozen: nn.Module, x: torch.Tensor) -> torch.Tensor:
        """``frozen(x)``, each image's map taken from the cache when it was computed before."""
        self._sync(frozen)
        keys = image_keys(x)
        table = self._rows.setdefault(input_signature(x), {})
        rows = [table.get(k, -1) for k in keys]
        miss = [i for i, r in enumerate(rows) if r < 0]
        self.hits += len(keys) - len(miss)
        self.misses += len(miss)
        layout = _memory_format(x)     # the layout frozen(x) has: later layers (dropout masks!) depend on it
        if not miss:
            return self._gather(rows).to(x.device, x.dtype).contiguous(memory_format=layout)
        computed = frozen(x if len(miss) == len(keys) else x[miss])
        self._remember(table, [keys[i] for i in miss], computed)
        if len(miss) == len(keys):
            return computed
        out = torch.empty((len(keys), *computed.shape[1:]), dtype=computed.dtype, device=computed.device)
        hit = [i for i, r in enumerate(rows) if r >= 0]
        out[hit] = self._gather([rows[i] for i in hit]).to(out.device, out.dtype)
        out[miss] = computed
        return out.contiguous(memory_format=layout)

    @contextlib.contextmanager
    def attached(self, backbone: nn.Module):
        """Use this cache for ``backbone``'s frozen blocks inside the ``with`` block (then detach it)."""
        attach(backbone, self)
        try:
            yield self
        finally:
            detach(backbone)

    def __deepcopy__(self, memo):
        return self      # copies of a model share the memo (it checks the frozen weights it is called with)


def attach(backbone: nn.Module, cache: FrozenFeatureCache) -> FrozenFeatureCache:
    """Make ``backbone`` (a :class:`vpr_nb.models.SmallCNN`) run its frozen blocks through ``cache``.

    Refused (``ValueError``) when the backbone has no frozen-block hook or its frozen blocks are not
    deterministic (:func:`check_cacheable`)."""

    if not isinstance(cache, FrozenFeatureCache):
        raise ValueError(f"cache must be a FrozenFeatureCache, got {type(cache).__name__}")
    if not isinstance(backbone, SmallCNN):
        raise ValueError(f"the frozen-block cache works with vpr_nb.models.SmallCNN backbones (the course "
                         f"backbone), got {type(backbone).__name__}")
    check_cacheable(backbone.features[:backbone.num_frozen])
    backbone.frozen_cache = cache
    return cache


def detach(backbone: nn.Module) -> None:
    """Run ``backbone``'s frozen blocks without a cache again."""
    if hasattr(backbone, "frozen_cache"):
        backbone.frozen_cache = None
