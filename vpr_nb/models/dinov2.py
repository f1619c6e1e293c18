"""The DINOv2 ViT backbone of DINOv2-SALAD, loaded from a local clone of ``facebookresearch/dinov2`` (never downloads)."""
from __future__ import annotations

import os
from pathlib import Path

import torch
from torch import nn

from .._checks import check_int
from .image_checks import _check_images

DINOV2_MODELS = ("dinov2_vits14", "dinov2_vitb14", "dinov2_vitl14", "dinov2_vitg14",
                 "dinov2_vits14_reg", "dinov2_vitb14_reg", "dinov2_vitl14_reg", "dinov2_vitg14_reg")
DINOV2_HUB_ENV = "VPR_NB_DINOV2_HUB"


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
