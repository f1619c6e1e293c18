"""Local InfoNCE (Eq. L) between the feature maps of two horizontally shifted views of the same images.

The dense form of van den Oord et al.'s InfoNCE, as in DenseCL (Wang et al., CVPR 2021): a term of the course
backbone's pretraining (:mod:`vpr_nb.pretrain`), :func:`local_infonce`.
"""
from __future__ import annotations

import torch
import torch.nn.functional as F

from .._checks import check_positive, check_tensor

LOCAL_NEGATIVES = ("image", "batch")   # local_infonce: a position's negatives come from its image / the batch


def local_infonce(full: torch.Tensor, shifted: torch.Tensor, offset: int, temperature: float = 0.1,
                  negatives: str = "image", max_anchors: int = 1024, generator: torch.Generator | None = None
                  ) -> torch.Tensor:
    """Local InfoNCE between the feature maps of two horizontally shifted views of the same images.

    ``full`` ``[B, C, h, w]`` is the map of the images, ``shifted`` ``[B, C, h, w']`` the map of the same images
    cropped by ``offset`` feature columns on the left, so that position (i, j) of ``shifted`` sees what position
    (i, j + offset) of ``full`` sees. With every feature L2-normalised, an anchor ``u_a`` at (i, j + offset) of
    ``full`` and its positive ``v_a`` at (i, j) of ``shifted``, the loss is the mean over anchors of

        ℓ_a = −log( exp(u_a·v_a / τ) / Σ_{c ∈ N(a)} exp(u_a·v_c / τ) )                           (L)

    where N(a) holds ``v_a`` and the negatives: every position of the same image's ``shifted`` map
    (``negatives="image"``: a feature must tell its position apart from the rest of its image) or the positives
    of the other anchors, from every image (``"batch"``; at most ``max_anchors`` anchors drawn with ``generator``).
    Minimising it spreads an image's local features apart while keeping them stable under a shift of the view:
    what NetVLAD's and SALAD's assignments need.
    """
    check_tensor(full, "full", ndim=4)
    check_tensor(shifted, "shifted", ndim=4)
    b, c, h, w = full.shape
    offset = int(offset)
    if shifted.shape[:3] != (b, c, h) or not 0 < offset < w:
        raise ValueError(f"shifted must be [B, C, h, w'] like full {tuple(full.shape)} and offset in [1, {w - 1}], "
                         f"got {tuple(shifted.shape)} and offset {offset}")
    check_positive(temperature, "temperature")
    if negatives not in LOCAL_NEGATIVES:
        raise ValueError(f"negatives must be one of {LOCAL_NEGATIVES}, got {negatives!r}")
    overlap = min(w - offset, shifted.shape[3])
    u = F.normalize(full[:, :, :, offset:offset + overlap], dim=1).flatten(2).transpose(1, 2)   # [B, h*ov, C]
    v_all = F.normalize(shifted, dim=1)
    if negatives == "image":
        logits = torch.bmm(u, v_all.flatten(2)) / temperature                                  # [B, h*ov, h*w']
        rows = torch.arange(h, device=full.device).repeat_interleave(overlap)
        cols = torch.arange(overlap, device=full.device).repeat(h)
        target = (rows * shifted.shape[3] + cols).expand(b, -1)
        return F.cross_entropy(logits.flatten(0, 1), target.flatten())
    v = v_all[:, :, :, :overlap].flatten(2).transpose(1, 2)                                     # [B, h*ov, C]
    u, v = u.flatten(0, 1), v.flatten(0, 1)
    keep = torch.randperm(len(u), generator=generator, device=u.device)[:max_anchors] if len(u) > max_anchors else None
    if keep is not None:
        u, v = u[keep], v[keep]
    logits = u @ v.T / temperature
    return F.cross_entropy(logits, torch.arange(len(u), device=u.device))
