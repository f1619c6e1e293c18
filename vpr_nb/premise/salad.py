"""SALAD's premise (notebook 05), measured: what the dustbin takes, per content label.

SALAD (Izquierdo & Civera, CVPR 2024) assigns the n local features of an image to m clusters by optimal
transport with a dustbin: the Sinkhorn plan of notebook 05's Eq. (2) on the scores augmented with a dustbin
row, under the marginals of Eq. (3) (each feature gives 1, each cluster receives 1, the dustbin the other
n − m); the descriptor sums the features under the plan without its dustbin row (Eqs. (4)-(5)). The premise:
the dustbin takes what does not identify the place (sky, ground, things that come and go), so the descriptor
sums what does. Two facts frame the measurement: by Eq. (3) the dustbin receives (n − m)/n of a feature's
mass on average whatever the scores (0.83 for the course's 96 positions and 16 clusters), and its one
learned score cancels in Eq. (2); only the score head decides *which* features it takes. So the question is
whether the share it takes differs by content:

- :func:`label_shares`: the pixel share of each content label (:data:`vpr_nb.synthetic.LABEL_NAMES`,
  ``make_dataset(..., labels=True)``);
- :func:`cell_labels`: the majority label of each cell of the feature map (stride × stride pixels);
- :func:`plan_dustbin_share` and :func:`dustbin_shares`: the share of each local feature's mass the plan
  sends to the dustbin, from a given plan or from a model with a SALAD aggregator;
- :func:`share_by_label` and :func:`dustbin_share_by_label`: that share averaged per content label;
- :func:`kept_mass_auc`, :func:`dustbin_auc` and :func:`rank_auc`: how well the kept mass (1 − the dustbin
  share) separates informative cells (``object``) from uninformative ones (``ground``, ``sky``, ``occluder``,
  ``distractor``): 0.5 = not at all, 1 = perfectly.
"""
from __future__ import annotations

import numpy as np
import torch
from scipy.stats import rankdata

from .._checks import check_int
from ..aggregation import SALAD, sinkhorn
from ..image_tensors import as_image_array, images_to_tensor
from ..synthetic.labels import LABEL_NAMES

SALAD_ITERS = 3                                   # Sinkhorn iterations of SALAD's forward (the published code's)
INFORMATIVE = ("object",)                         # what identifies a place ...
UNINFORMATIVE = ("ground", "sky", "occluder", "distractor")   # ... and what does not (the skyline: neither)


def _check_labels(labels, name: str = "labels") -> np.ndarray:
    """Integer label maps (N, H, W) (or one (H, W) map) with values in range, as int64 (N, H, W)."""
    lab = np.asarray(labels)
    if lab.ndim == 2:
        lab = lab[None]
    if lab.ndim != 3 or lab.size == 0:
        raise ValueError(f"{name} must be non-empty integer label maps (N, H, W), got shape {lab.shape}")
    if not np.issubdtype(lab.dtype, np.integer):
        raise ValueError(f"{name} must hold integer labels (make_dataset(..., labels=True)), got dtype {lab.dtype}")
    if lab.min() < 0 or lab.max() >= len(LABEL_NAMES):
        raise ValueError(f"{name} holds labels outside 0..{len(LABEL_NAMES) - 1} ({', '.join(LABEL_NAMES)}): "
                         f"found {lab.min()}..{lab.max()}")
    return lab.astype(np.int64)


def _check_names(names, name: str) -> tuple[str, ...]:
    names = (names,) if isinstance(names, str) else tuple(names)
    bad = [n for n in names if n not in LABEL_NAMES]
    if bad or not names:
        raise ValueError(f"{name} must be a non-empty list of label names from {LABEL_NAMES}, got {names}")
    return names


def label_shares(labels) -> dict[str, float]:
    """The share of the pixels of ``labels`` (N, H, W) that carry each content label, by name; sums to 1."""
    lab = _check_labels(labels)
    counts = np.bincount(lab.ravel(), minlength=len(LABEL_NAMES))
    return {n: float(c) / lab.size for n, c in zip(LABEL_NAMES, counts)}


def cell_labels(labels, cells: tuple[int, int]) -> np.ndarray:
    """The majority label (N, h, w) of each cell when the maps (N, H, W) are cut into ``cells = (h, w)`` cells
    of (H / h) × (W / w) pixels (a feature map's positions: 4 × 4 pixels for the course backbone's stride 4).
    Ties go to the lower label id (object before ground before skyline, ...)."""
    lab = _check_labels(labels)
    n, H, W = lab.shape
    if len(tuple(cells)) != 2:
        raise ValueError(f"cells must be (h, w), the feature map's size, got {cells!r}")
    h, w = (check_int(c, "cells") for c in cells)
    if H % h or W % w or H // h != W // w:
        raise ValueError(f"label maps of {H}x{W} pixels do not split into {h}x{w} square cells: the feature map "
                         f"must come from the images through one integer stride")
    s = H // h
    blocks = lab.reshape(n, h, s, w, s).transpose(0, 1, 3, 2, 4).reshape(n, h, w, s * s)
    counts = (blocks[..., None] == np.arange(len(LABEL_NAMES))).sum(-2)              # (N, h, w, labels)
    return counts.argmax(-1)


def plan_dustbin_share(plan) -> np.ndarray:
    """The share of each feature's mass that a transport ``plan`` [B, m+1, n] (or [m+1, n]; not in log space,
    dustbin row last, as ``sinkhorn(...).exp()``) sends to the dustbin: ``P[m, i] / Σ_k P[k, i]``, float64
    [B, n]. After SALAD's last Sinkhorn update (Eq. (2)) every column sums to 1, so this is ``P[m, i]``."""
    p = plan.detach().cpu().double().numpy() if isinstance(plan, torch.Tensor) else np.asarray(plan, dtype=float)
    if p.ndim == 2:
        p = p[None]
    if p.ndim != 3 or p.shape[1] < 2 or p.shape[0] == 0 or p.shape[2] == 0:
        raise ValueError(f"plan must be [B, m+1, n] with at least one cluster row and the dustbin row, got {p.shape}")
    if not np.isfinite(p).all() or (p < 0).any():
        raise ValueError("plan must hold finite non-negative masses (pass exp of sinkhorn's log plan)")
    total = p.sum(1)
    if (total <= 0).any():
        raise ValueError("plan has a feature (column) without mass")
    return p[:, -1, :] / total


def _salad_of(model) -> SALAD:
    agg = getattr(model, "aggregator", None)
    if not isinstance(agg, SALAD) or not hasattr(getattr(model, "backbone", None), "forward_with_token"):
        raise ValueError("needs a VPRModel with a SALAD aggregator (build_model(..., 'salad') or "
                         "vpr_nb.recipe.build_start(Method('SALAD', 'salad'), ...))")
    if agg.assignment != "sinkhorn":
        raise ValueError(f"this SALAD assigns by {agg.assignment!r}, which has no dustbin; "
                         f"measure a SALAD with assignment='sinkhorn'")
    return agg


def dustbin_shares(model, images, batch_size: int = 256) -> np.ndarray:
    """The share of each local feature's mass that SALAD's plan (Eqs. (2)-(3), 3 iterations, as in its
    forward) sends to the dustbin, float64 (N, h, w) over the feature map of each of the uint8 ``images``
    (N, H, W, 3). Runs in eval mode (no dropout) without gradients; the model's modes are restored."""
    agg = _salad_of(model)
    arr = as_image_array(images)
    if len(arr) == 0:
        raise ValueError("images is empty: it needs at least one image")
    batch_size = check_int(batch_size, "batch_size")
    modes = [(m, m.training) for m in model.modules()]
    model.eval()
    out = []
    try:
        with torch.no_grad():
            for start in range(0, len(arr), batch_size):
                fmap, _ = model.backbone.forward_with_token(images_to_tensor(arr[start:start + batch_size]))
                plan = sinkhorn(agg.score(fmap).flatten(2), agg.dust_bin, SALAD_ITERS).exp()   # [B, m+1, n]
                out.append(plan_dustbin_share(plan).reshape(len(fmap), *fmap.shape[2:]))
    finally:
        for m, mode in modes:
            m.training = mode
    return np.concatenate(out)


def _cells_of(shares, labels) -> tuple[np.ndarray, np.ndarray]:
    """``shares`` (N, h, w) as float64 and the majority labels of ``labels`` (N, H, W) on the same cells."""
    sh = np.asarray(shares, dtype=float)
    if sh.ndim == 2:
        sh = sh[None]
    lab = _check_labels(labels)
    if sh.ndim != 3 or sh.shape[0] != lab.shape[0]:
        raise ValueError(f"shares {sh.shape} and labels {lab.shape} must cover the same N images, as (N, h, w) "
                         f"and (N, H, W)")
    if not np.isfinite(sh).all():
        raise ValueError("shares must be finite")
    return sh, cell_labels(lab, sh.shape[1:])


def share_by_label(shares, labels) -> dict[str, float]:
    """The mean of per-cell ``shares`` (N, h, w) over the cells of each content label (the majority label of
    the cell's pixels in ``labels`` (N, H, W), :func:`cell_labels`), by name; NaN for a label no cell has."""
    sh, cells = _cells_of(shares, labels)
    return {n: float(sh[cells == k].mean()) if (cells == k).any() else float("nan")
            for k, n in enumerate(LABEL_NAMES)}


def dustbin_share_by_label(model, images, labels, batch_size: int = 256) -> dict[str, float]:
    """The share of a local feature's mass that SALAD's dustbin takes, averaged per content label of its cell
    (:func:`dustbin_shares`, :func:`share_by_label`). Flat (every label near (n − m)/n) = the dustbin does not
    tell content apart; the premise holds where uninformative labels get more than ``object``."""
    arr = as_image_array(images)
    lab = _check_labels(labels)
    if lab.shape != arr.shape[:3]:
        raise ValueError(f"labels {lab.shape} must be one (H, W) map per image of images {arr.shape}")
    return share_by_label(dustbin_shares(model, arr, batch_size), lab)


def rank_auc(positive, negative) -> float:
    """The area under the ROC curve of scores that should be higher for ``positive`` than for ``negative``:
    the Mann-Whitney probability that a random positive outranks a random negative (ties count half), from
    the pooled ranks (``scipy.stats.rankdata``). 1 = perfect separation, 0.5 = none."""
    pos, neg = np.asarray(positive, dtype=float).ravel(), np.asarray(negative, dtype=float).ravel()
    if len(pos) == 0 or len(neg) == 0:
        raise ValueError(f"the AUC needs at least one positive and one negative, got {len(pos)} and {len(neg)}")
    if not (np.isfinite(pos).all() and np.isfinite(neg).all()):
        raise ValueError("scores must be finite")
    ranks = rankdata(np.concatenate([pos, neg]))
    return float((ranks[:len(pos)].sum() - len(pos) * (len(pos) + 1) / 2) / (len(pos) * len(neg)))


def kept_mass_auc(shares, labels, informative=INFORMATIVE, uninformative=UNINFORMATIVE) -> float:
    """AUC (:func:`rank_auc`) of the kept mass, 1 − the dustbin share per cell (``shares`` (N, h, w)), for
    telling cells whose majority label is ``informative`` from cells whose label is ``uninformative``
    (``labels`` (N, H, W)); cells of other labels are left out."""
    informative, uninformative = _check_names(informative, "informative"), _check_names(uninformative, "uninformative")
    if set(informative) & set(uninformative):
        raise ValueError(f"informative {informative} and uninformative {uninformative} must not share a label")
    sh, cells = _cells_of(shares, labels)
    ids = {n: k for k, n in enumerate(LABEL_NAMES)}
    pos = np.isin(cells, [ids[n] for n in informative])
    neg = np.isin(cells, [ids[n] for n in uninformative])
    return rank_auc(1 - sh[pos], 1 - sh[neg])


def dustbin_auc(model, images, labels, informative=INFORMATIVE, uninformative=UNINFORMATIVE,
                batch_size: int = 256) -> float:
    """How well SALAD's dustbin separates content: :func:`kept_mass_auc` of the model's dustbin shares
    (:func:`dustbin_shares`) on ``images`` with their ``labels``. 1 = it keeps every informative cell's mass
    more than any uninformative cell's; 0.5 = it keeps both alike (the dustbin has learned nothing)."""
    arr = as_image_array(images)
    lab = _check_labels(labels)
    if lab.shape != arr.shape[:3]:
        raise ValueError(f"labels {lab.shape} must be one (H, W) map per image of images {arr.shape}")
    return kept_mass_auc(dustbin_shares(model, arr, batch_size), lab, informative, uninformative)
