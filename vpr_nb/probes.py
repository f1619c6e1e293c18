"""Probes: how much a world and a backbone leave for an aggregator or a batch sampler to work with.

Two measurements, each testing one paper's premise on the course's data:

**Local-feature probe** (SALAD's premise: many *diverse* local features to assign to clusters).
The local features are the C-vectors ``f_{b,p}`` of a backbone's output map ``[B, C, h, w]`` at every
position p of every image b: ``course_backbone()`` gives its output (after the final ReLU, what the recipe's
NetVLAD and SALAD read), ``course_backbone(final_relu=False)`` the features before that ReLU (where the
pretraining's local term acts).

* :func:`effective_dimension` -- pool the features of all images and positions into ``N = B·h·w`` rows;
  by default (``normalize=True``) each row is L2-normalised to its direction ``u = f / |f|`` (what
  NetVLAD's per-feature normalisation and a cosine see; all-zero rows have no direction and are left
  out). The rows are **centred** (their mean over all N rows subtracted) and their covariance
  ``Σ = (1/N) Σ_n (u_n − ū)(u_n − ū)^T`` has eigenvalues ``λ_1 ≥ … ≥ λ_C``. The effective dimension is
  the participation ratio

      PR = (Σ_k λ_k)² / Σ_k λ_k²                                                     (1)

  (C for an isotropic cloud, 1 when all variance lies along one axis), and ``dims`` is the smallest
  k with ``λ_1 + … + λ_k ≥ variance · Σ_k λ_k`` (90 % by default). ``normalize=False`` uses the raw
  features (then a few high-norm channels dominate).
* :func:`within_image_cosine` -- for every image, the mean cosine similarity over the ordered pairs
  p ≠ q of its non-zero local features, ``(|Σ_p u_p|² − m) / (m (m − 1))`` with m such features, then
  the mean over images (images with m < 2 are left out). **Not centred**: a component every feature
  of an image shares (a bias, a global colour) raises it towards 1, as it does for SALAD's clusters.

**Near-duplicate probe** (CliqueMining's premise: a batch of places a few metres apart teaches the
embedding to order neighbours -- only if such places are *not* near-duplicates).
On a route split the database image ``d_i`` (reference condition) and the query ``q_i`` (the other
season) belong to the same frame i (``q_utm == db_utm``). With frames ``s`` metres apart and a step
of ``k·s`` metres, :func:`near_duplicate_rate` is the fraction of frames i (with frame i + k in the
split, ``k·s`` metres away along the track) for which

      ‖a_i − a_{i+k}‖ < ‖d_i − q_i‖                                                 (2)

where ``a = d`` (``anchor="database"``, the default) or ``a = q``: the same-season frame one step
ahead is closer in descriptor space than the frame's own cross-season positive, so a loss that treats
it as a negative pushes apart views that differ *less* than the positives do. The clique step of
notebook 07's route (frames 2.5 m apart, same-place threshold 1.01 × 2.5 m) is 5 m: the nearest
negative a clique batch holds. :func:`near_duplicate_probe` evaluates Eq. (2) for raw pixels or a
model on a split, at several steps.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch

from ._checks import as_float_matrix, as_utm, check_int, check_positive, check_tensor
from .evaluation import as_image_array, compute_descriptors, images_to_tensor, raw_pixel_descriptors

ANCHORS = ("database", "query")


# ------------------------------------------------------------------------------ local features
def _as_feature_rows(features, name: str = "features") -> np.ndarray:
    """``[N, C]`` rows (float64) from an ``[N, C]`` array or a ``[B, C, h, w]`` feature map."""
    if isinstance(features, torch.Tensor):
        check_tensor(features, name, ndim=(2, 4))
        features = features.detach().cpu().double().numpy()
    arr = np.asarray(features)
    if arr.ndim == 4:
        arr = arr.transpose(0, 2, 3, 1).reshape(-1, arr.shape[1])
    elif arr.ndim != 2:
        raise ValueError(f"{name} must be local features [N, C] or a feature map [B, C, h, w], got shape {arr.shape}")
    return as_float_matrix(arr, name).astype(np.float64)


def _as_map(maps, name: str = "maps") -> np.ndarray:
    """A finite float64 ``[B, C, h, w]`` array."""
    if isinstance(maps, torch.Tensor):
        check_tensor(maps, name, ndim=4)
        maps = maps.detach().cpu().double().numpy()
    arr = np.asarray(maps)
    if arr.ndim != 4 or 0 in arr.shape:
        raise ValueError(f"{name} must be a non-empty feature map [B, C, h, w], got shape {arr.shape}")
    if not np.issubdtype(arr.dtype, np.floating) or not np.isfinite(arr).all():
        raise ValueError(f"{name} must hold finite floating-point values (dtype {arr.dtype})")
    return arr.astype(np.float64)


@dataclass(frozen=True)
class EffectiveDimension:
    """Eq. (1): ``participation_ratio`` and ``dims`` (eigenvalues that hold ``variance`` of the total)."""

    participation_ratio: float
    dims: int
    variance: float
    eigenvalues: np.ndarray          # descending


def effective_dimension(features, *, normalize: bool = True, variance: float = 0.9) -> EffectiveDimension:
    """Participation ratio (Eq. 1 of the module docstring) of the centred covariance of local features.

    ``features``: ``[N, C]`` rows or a feature map ``[B, C, h, w]`` (pooled over images and positions).
    ``normalize``: L2-normalise every row first (the default; all-zero rows are dropped); ``variance``
    in (0, 1]: the share of the total variance that ``dims`` eigen-directions must hold.
    """
    if not isinstance(normalize, bool):
        raise ValueError(f"normalize must be True or False, got {normalize!r}")
    v = check_positive(variance, "variance")
    if v > 1:
        raise ValueError(f"variance is a share of the total variance in (0, 1], got {variance}")
    x = _as_feature_rows(features)
    if normalize:
        norms = np.linalg.norm(x, axis=1)
        x = x[norms > 0] / norms[norms > 0, None]
    if len(x) < 2:
        raise ValueError(f"effective_dimension needs at least 2 (non-zero) local features, got {len(x)}")
    x = x - x.mean(axis=0)
    lam = np.clip(np.linalg.eigvalsh(x.T @ x / len(x))[::-1], 0.0, None)
    total = lam.sum()
    if total <= 0:
        raise ValueError("the local features do not vary (every feature is the same vector): "
                         "the effective dimension is undefined")
    dims = int(np.searchsorted(np.cumsum(lam) / total, v * (1 - 1e-12)) + 1)
    return EffectiveDimension(float(total ** 2 / (lam ** 2).sum()), min(dims, len(lam)), v, lam)


def within_image_cosine(maps) -> float:
    """Mean over images of the mean cosine between two distinct (non-zero) local features of the image.

    ``maps``: ``[B, C, h, w]``. Uncentred (see the module docstring). Images with fewer than two
    non-zero features are left out; a ValueError if none is left."""
    f = _as_map(maps)
    b, c = f.shape[:2]
    u = f.reshape(b, c, -1)
    norms = np.linalg.norm(u, axis=1, keepdims=True)            # [B, 1, n]
    u = np.divide(u, norms, out=np.zeros_like(u), where=norms > 0)
    m = (norms[:, 0] > 0).sum(axis=1)                            # non-zero features per image
    keep = m >= 2
    if not keep.any():
        raise ValueError("no image has two non-zero local features: within-image cosine is undefined "
                         "(read the map before the final ReLU)")
    s = u.sum(axis=2)
    cos = ((s * s).sum(axis=1) - m) / np.maximum(m * (m - 1), 1)
    return float(cos[keep].mean())


@torch.no_grad()
def local_feature_maps(backbone: torch.nn.Module, images, batch_size: int = 256) -> torch.Tensor:
    """``backbone``'s output maps ``[N, C, h, w]`` (float32, eval mode, no autograd) for uint8 images
    ``(N, H, W, 3)``; the backbone's mode is restored afterwards."""

    if not isinstance(backbone, torch.nn.Module):
        raise ValueError(f"backbone must be a torch.nn.Module, got {type(backbone).__name__}")
    batch_size = check_int(batch_size, "batch_size")
    arr = as_image_array(images)
    if len(arr.shape) != 4 or arr.shape[0] == 0:
        raise ValueError(f"images must be a non-empty (N, H, W, 3) uint8 array, got shape {arr.shape}")
    was_training = backbone.training
    backbone.eval()
    try:
        device = next(backbone.parameters()).device
        out = [backbone(images_to_tensor(arr[i:i + batch_size]).to(device)).float().cpu()
               for i in range(0, arr.shape[0], batch_size)]
    finally:
        backbone.train(was_training)
    return torch.cat(out)


def local_feature_probe(backbone: torch.nn.Module, images, variance: float = 0.9) -> dict:
    """The local-feature probe of ``backbone`` on ``images`` (e.g. a split's database and queries):
    ``{"effective dimension", "dims for 90% variance", "within-image cosine", "features"}``
    (normalised, centred Eq. 1; uncentred cosine). Pass ``course_backbone(final_relu=False)`` to read
    the course backbone before its final ReLU, ``course_backbone()`` for its output."""
    maps = local_feature_maps(backbone, images)
    ed = effective_dimension(maps, variance=variance)
    return {"effective dimension": ed.participation_ratio, f"dims for {100 * ed.variance:g}% variance": ed.dims,
            "within-image cosine": within_image_cosine(maps), "features": int(maps.shape[0] * maps[0, 0].numel())}


# ------------------------------------------------------------------------------ near duplicates
def _frame_offset(utm: np.ndarray, step: float, tolerance: float) -> tuple[int, np.ndarray]:
    """(k, the frames i whose frame i + k lies ``step`` metres away within ``tolerance`` × spacing)."""
    gaps = np.linalg.norm(np.diff(utm, axis=0), axis=1)
    spacing = float(np.median(gaps))
    if not spacing > 0:
        raise ValueError("consecutive database geotags coincide: the split is not a route of distinct frames")
    k = int(round(step / spacing))
    if k < 1 or abs(k * spacing - step) > tolerance * spacing:
        raise ValueError(f"step {step:g} m is not a multiple of the frame spacing {spacing:.3g} m; "
                         f"use e.g. {spacing:.3g}, {2 * spacing:.3g} or {4 * spacing:.3g}")
    i = np.arange(len(utm) - k)
    apart = np.linalg.norm(utm[i + k] - utm[i], axis=1)
    return k, i[np.abs(apart - step) <= tolerance * spacing]      # drops pairs across a split gap


def near_duplicate_rate(db_desc, q_desc, utm, step: float, *, anchor: str = "database",
                        tolerance: float = 0.25) -> float:
    """Eq. (2) of the module docstring: the fraction of frames whose same-season frame ``step`` metres
    ahead is closer in descriptor space than their cross-season positive.

    ``db_desc[i]`` and ``q_desc[i]`` are the two seasons' descriptors of frame i, ``utm[i]`` its geotag
    (frames in track order, as a route split holds them); ``step`` must be a whole number of frame
    spacings (the median distance between consecutive frames), within ``tolerance`` × spacing; frame
    pairs whose geotags are not ``step`` metres apart (a gap between splits) are left out.
    """
    if anchor not in ANCHORS:
        raise ValueError(f"anchor must be one of {ANCHORS}, got {anchor!r}")
    db = as_float_matrix(db_desc, "db_desc").astype(np.float64)
    q = as_float_matrix(q_desc, "q_desc", dim=db.shape[1]).astype(np.float64)
    utm = as_utm(utm, "utm")
    if not (len(db) == len(q) == len(utm)):
        raise ValueError(f"db_desc ({len(db)}), q_desc ({len(q)}) and utm ({len(utm)}) must have one row per frame")
    if len(utm) < 2:
        raise ValueError("a route needs at least 2 frames")
    step = check_positive(step, "step")
    tolerance = check_positive(tolerance, "tolerance")
    if tolerance >= 0.5:
        raise ValueError(f"tolerance must be below 0.5 frame spacings, got {tolerance}")
    k, i = _frame_offset(utm, step, tolerance)
    if len(i) == 0:
        raise ValueError(f"no two frames of the split lie {step:g} m apart; use a smaller step")
    a = db if anchor == "database" else q
    return float(np.mean(np.linalg.norm(a[i] - a[i + k], axis=1) < np.linalg.norm(db[i] - q[i], axis=1)))


def near_duplicate_probe(split, model: torch.nn.Module | None = None, steps: Sequence[float] = (2.5, 5.0, 10.0),
                         anchor: str = "database") -> dict[float, float]:
    """:func:`near_duplicate_rate` at every step (metres) on a route ``split``, for ``model``'s
    descriptors (:func:`vpr_nb.evaluation.compute_descriptors`) or, with ``model=None``, raw pixels
    (:func:`vpr_nb.evaluation.raw_pixel_descriptors`). Returns ``{step: fraction}``."""

    for name in ("db_images", "q_images", "db_utm", "q_utm"):
        if not hasattr(split, name):
            raise ValueError(f"split must provide {name} (a route VPRDataset split)")
    du, qu = as_utm(split.db_utm, "split.db_utm"), as_utm(split.q_utm, "split.q_utm")
    if du.shape != qu.shape or not np.allclose(du, qu):
        raise ValueError("the near-duplicate probe needs a route split whose query i is tagged at database "
                         "frame i (q_utm == db_utm); a city split has no frames")
    if model is None:
        db, q = raw_pixel_descriptors(split.db_images), raw_pixel_descriptors(split.q_images)
    elif isinstance(model, torch.nn.Module):
        db, q = compute_descriptors(model, split.db_images), compute_descriptors(model, split.q_images)
    else:
        raise ValueError(f"model must be a torch.nn.Module or None (raw pixels), got {type(model).__name__}")
    steps = tuple(steps)
    if not steps:
        raise ValueError("steps is empty: give at least one step in metres, e.g. (2.5, 5.0, 10.0)")
    return {float(s): near_duplicate_rate(db, q, du, s, anchor=anchor) for s in steps}
