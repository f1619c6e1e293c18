"""Backbones and the VPR model wrapper: image ``[B, 3, H, W]`` → local feature map → global descriptor.

- :class:`SmallCNN`: a 4-layer CNN (total stride 4) that trains at >1000 images/s on a 2-core CPU
  on the course's 32×48 synthetic images; the notebooks' default.
- :class:`VGG16Backbone`: VGG16 up to conv5_3, the NetVLAD backbone (Arandjelović et al., CVPR 2016),
  loading torchvision's ``vgg16-397923af.pth`` without importing torchvision.
- :class:`DINOv2Backbone` and :func:`load_dinov2`: the DINOv2 ViT-B/14 of DINOv2-SALAD
  (Izquierdo & Civera, CVPR 2024), from a local clone of ``facebookresearch/dinov2`` (never downloads).
- :class:`VPRModel` and :func:`build_model`: backbone + aggregator (:mod:`vpr_nb.aggregation`).

Every backbone has ``out_channels`` (C) and ``stride``, and ``forward(x)`` returns the feature map
``[B, C, H/stride, W/stride]``. Backbones with a global token (SmallCNN, DINOv2) also have
``forward_with_token(x) -> (feature map, token [B, C])``, which aggregators that set
``needs_token = True`` (SALAD) receive.

Images are float ``[B, 3, H, W]`` tensors, ImageNet-normalised as
:func:`vpr_nb.evaluation.images_to_tensor` makes them.
"""
from __future__ import annotations

import math
import os
import re
from collections.abc import Mapping
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from ._checks import check_int, check_tensor, validated_inputs
from .kernels import apply_in_process

apply_in_process()          # pinned kernels (vpr_nb.kernels): convolutions without oneDNN, the same on every CPU

BACKBONE_NAMES = ("small_cnn", "vgg16", "dinov2")   # the keys of BACKBONES (defined below its classes)
DINOV2_MODELS = ("dinov2_vits14", "dinov2_vitb14", "dinov2_vitl14", "dinov2_vitg14",
                 "dinov2_vits14_reg", "dinov2_vitb14_reg", "dinov2_vitl14_reg", "dinov2_vitg14_reg")
DINOV2_HUB_ENV = "VPR_NB_DINOV2_HUB"
VGG16_WEIGHTS_URL = "https://download.pytorch.org/models/vgg16-397923af.pth"


def _check_images(x, name: str, channels: int, *, multiple_of: int = 1, min_size: int = 1) -> torch.Tensor:
    """Validate a finite float image batch ``[B, channels, H, W]`` (B ≥ 1, H and W ≥ ``min_size``,
    multiples of ``multiple_of``)."""
    check_tensor(x, name, ndim=4)
    b, c, h, w = x.shape
    if c != channels:
        raise ValueError(f"{name} must have {channels} channels ([B, {channels}, H, W]), got shape {tuple(x.shape)}; "
                         f"convert uint8 NHWC images with vpr_nb.evaluation.images_to_tensor")
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


# ------------------------------------------------------------------------------------------ SmallCNN


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
                  nn.Conv2d(2 * width, self.out_channels, 1)]
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


# --------------------------------------------------------------------------------------------- VGG16

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


# ------------------------------------------------------------------------------------ weight files

_UNSUPPORTED_GLOBAL = re.compile(r"Unsupported global: GLOBAL ([\w.]+)")


def read_weights(path, what: str = "checkpoint") -> Mapping:
    """Read a torch weights file with ``torch.load(path, map_location="cpu", weights_only=True)``.

    The one reader of weight files (checkpoints, the course backbone, VGG16 weights). Errors are one
    line naming the file: :class:`FileNotFoundError` when it is missing; :class:`ValueError` when it
    holds pickled Python objects (it is not a weights-only file and is never unpickled, since unpickling
    runs code from the file), when it is truncated or not a torch file, or when it holds no mapping.
    ``what`` names the file's role in the messages ("checkpoint", "course backbone", ...).
    """
    import pickle

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no {what} at {path}; check the path")
    if path.stat().st_size == 0:
        raise ValueError(f"{path} is empty (0 bytes), not a torch {what}: restore it or write it again")
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as exc:
        with open(path, "rb") as f:
            head = f.read(4)
        if head != b"PK\x03\x04" and head[:1] != b"\x80":   # neither torch's zip archive nor its legacy pickle
            raise ValueError(f"{path} is not a readable torch {what} ({path.stat().st_size} bytes, not a torch "
                             f"archive): the file is truncated or corrupted, or was not written by torch.save; "
                             f"restore it or write it again") from None
        m = _UNSUPPORTED_GLOBAL.search(str(exc))
        held = (f"pickled Python objects (class {m.group(1)})" if m else
                "data that is not plain tensors and containers (or a corrupted file)")
        raise ValueError(f"{path} is not a weights-only {what}: it holds {held}, and vpr_nb will not unpickle it "
                         f"(unpickling can run code from the file). If you trust the code that made it, re-save "
                         f"only its tensors there, e.g. torch.save(model.state_dict(), path)") from None
    except PermissionError:
        raise
    except Exception as exc:  # noqa: BLE001 - torch raises RuntimeError, OSError, EOFError, KeyError... on bad bytes
        first = str(exc).split(". ")[0].strip()[:120] or "no detail"
        raise ValueError(f"{path} is not a readable torch {what} ({type(exc).__name__}: {first}): the file is "
                         f"truncated or corrupted, or was not written by torch.save; restore it or write it "
                         f"again") from None
    if not isinstance(state, Mapping):
        raise ValueError(f"{path} holds a {type(state).__name__}, not a state dict (a mapping name -> tensor) "
                         f"as a {what} is")
    return state


def _few(keys, n: int = 3) -> str:
    keys = list(keys)
    return ", ".join(keys[:n]) + (f", ... ({len(keys)} in all)" if len(keys) > n else "")


def load_state_checked(module: nn.Module, state, source, *, hint: str | None = None) -> nn.Module:
    """``module.load_state_dict(state)`` after checking that ``state`` fits ``module`` exactly.

    ``state`` must hold the module's keys, no others, each a tensor of the module's shape (dtypes are
    cast as ``load_state_dict`` does). Otherwise a one-line :class:`ValueError` names ``source`` (the
    file or object the state came from), the missing and unexpected keys and the first shape mismatches
    (file vs model), then ``hint`` (default: build the model with the settings the weights were
    trained with). Returns ``module``.
    """
    if not isinstance(state, Mapping):
        raise ValueError(f"{source} holds a {type(state).__name__}, not a state dict (a mapping name -> tensor)")
    own = module.state_dict()
    missing = [k for k in own if k not in state]
    unexpected = [str(k) for k in state if k not in own]
    wrong = [f"{k} is {type(state[k]).__name__}, not a tensor" for k in own
             if k in state and not isinstance(state[k], torch.Tensor)]
    wrong += [f"{k} is {tuple(state[k].shape)} in the file but {tuple(own[k].shape)} in the model" for k in own
              if k in state and isinstance(state[k], torch.Tensor) and state[k].shape != own[k].shape]
    if not (missing or unexpected or wrong):
        module.load_state_dict(state)
        return module
    parts = []
    if wrong:
        parts.append(f"{len(wrong)} tensor(s) differ: {_few(wrong, 2)}")
    if missing:
        parts.append(f"{len(missing)} key(s) of the model are missing: {_few(missing)}")
    if unexpected:
        parts.append(f"{len(unexpected)} key(s) are not in the model: {_few(unexpected)}")
    if hint is None:
        if missing and unexpected and all(k.startswith("module.") for k in unexpected):
            hint = "the keys carry DistributedDataParallel's 'module.' prefix: strip it before loading"
        else:
            hint = ("the weights were written for another architecture or width: build the model with the "
                    "settings they were trained with (e.g. the run's config.json)")
    raise ValueError(f"{source} does not fit this {type(module).__name__}: {'; '.join(parts)}; {hint}")


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


# -------------------------------------------------------------------------------------------- DINOv2


class DINOv2Backbone(nn.Module):
    """A DINOv2 ViT as a VPR backbone, as in DINOv2-SALAD (Izquierdo & Civera, CVPR 2024, Sec. 4.1).

    ``vit`` is a ``DinoVisionTransformer`` from ``facebookresearch/dinov2`` (or any module with its
    interface: ``prepare_tokens_with_masks``, ``blocks``, ``norm``, ``patch_size``, ``embed_dim`` and
    optionally ``num_register_tokens``). The patch embedding and the first ``len(blocks) − k`` blocks
    are frozen and run under ``torch.no_grad()``; the last ``k = num_trainable_blocks`` blocks and the
    final LayerNorm train. The normalised tokens are split into the CLS token ``[B, C]`` and the patch
    tokens, reshaped to a map ``[B, C, H/14, W/14]`` (register tokens are dropped).
    """

    def __init__(self, vit: nn.Module, num_trainable_blocks: int = 4) -> None:
        super().__init__()
        needed = ("prepare_tokens_with_masks", "blocks", "norm", "patch_size", "embed_dim")
        lacking = [a for a in needed if not hasattr(vit, a)]
        if not isinstance(vit, nn.Module) or lacking:
            raise ValueError(f"vit must be a DINOv2 DinoVisionTransformer; it lacks {', '.join(lacking) or 'nn.Module'}")
        self.vit = vit
        self.num_trainable_blocks = check_int(num_trainable_blocks, "num_trainable_blocks", minimum=0,
                                              maximum=len(vit.blocks))
        self.out_channels = int(vit.embed_dim)
        self.stride = int(vit.patch_size)
        self.num_register_tokens = int(getattr(vit, "num_register_tokens", 0))
        self.num_frozen = len(vit.blocks) - self.num_trainable_blocks
        vit.requires_grad_(False)
        vit.blocks[self.num_frozen:].requires_grad_(True)
        vit.norm.requires_grad_(True)

    def forward_with_token(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``x`` ``[B, 3, H, W]`` (H, W multiples of 14) → (patch map ``[B, C, H/14, W/14]``, CLS ``[B, C]``)."""
        _check_images(x, "x", 3, multiple_of=self.stride)
        b, _, h, w = x.shape
        with torch.no_grad():
            tokens = self.vit.prepare_tokens_with_masks(x)
            for block in self.vit.blocks[:self.num_frozen]:
                tokens = block(tokens)
        for block in self.vit.blocks[self.num_frozen:]:
            tokens = block(tokens)
        tokens = self.vit.norm(tokens)
        patches = tokens[:, 1 + self.num_register_tokens:]
        fmap = patches.reshape(b, h // self.stride, w // self.stride, self.out_channels).permute(0, 3, 1, 2)
        return fmap, tokens[:, 0]

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """``x`` → patch feature map ``[B, C, H/14, W/14]`` (see :meth:`forward_with_token`)."""
        return self.forward_with_token(x)[0]


def _dinov2_checkpoint(model: str) -> Path:
    """Where ``torch.hub`` looks for ``model``'s weights (``<hub dir>/checkpoints/<name>_pretrain.pth``)."""
    full_name = model + "4" if model.endswith("_reg") else model  # the _reg models have 4 register tokens
    return Path(torch.hub.get_dir()) / "checkpoints" / f"{full_name}_pretrain.pth"


def load_dinov2(hub_dir=None, model: str = "dinov2_vitb14", num_trainable_blocks: int = 4) -> DINOv2Backbone:
    """Load a pretrained DINOv2 from a local clone with ``torch.hub.load(..., source="local")``.

    ``hub_dir`` (or the environment variable ``VPR_NB_DINOV2_HUB``) is a clone of
    https://github.com/facebookresearch/dinov2; the weights must already be in torch's hub cache
    (``torch.hub.get_dir()/checkpoints``). Nothing is downloaded: a missing clone or weight file
    raises :class:`FileNotFoundError` saying how to provide it. Returns a :class:`DINOv2Backbone`
    with the last ``num_trainable_blocks`` blocks trainable (4 in DINOv2-SALAD).
    """
    if model not in DINOV2_MODELS:
        raise ValueError(f"unknown DINOv2 model {model!r}; valid names are {', '.join(DINOV2_MODELS)}")
    hub_dir = hub_dir if hub_dir is not None else os.environ.get(DINOV2_HUB_ENV)
    if hub_dir is None or not (Path(hub_dir) / "hubconf.py").is_file():
        where = "no hub_dir given" if hub_dir is None else f"{hub_dir} has no hubconf.py"
        raise FileNotFoundError(
            f"DINOv2 code not found ({where}). Clone it once with "
            f"`git clone https://github.com/facebookresearch/dinov2` and pass its path as hub_dir "
            f"or set the environment variable {DINOV2_HUB_ENV} to it.")
    checkpoint = _dinov2_checkpoint(model)
    if not checkpoint.is_file():
        raise FileNotFoundError(
            f"DINOv2 weights not found at {checkpoint}. Download "
            f"https://dl.fbaipublicfiles.com/dinov2/{model.removesuffix('_reg')}/{checkpoint.name} "
            f"into {checkpoint.parent} (the torch hub cache; set TORCH_HOME to move it).")
    vit = torch.hub.load(str(hub_dir), model, source="local")
    return DINOv2Backbone(vit, num_trainable_blocks)


# ------------------------------------------------------------------------------------------ VPRModel


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
    from .aggregation import make_aggregator

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
    from .aggregation import NetVLAD, kmeans_centroids, sample_local_descriptors
    from .evaluation import as_image_array, images_to_tensor

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
    from .aggregation import SALAD
    from .evaluation import as_image_array, images_to_tensor

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
