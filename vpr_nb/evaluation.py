"""Retrieval and Recall@N, the evaluation protocol of every VPR paper in the course.

Protocol (as in NetVLAD, gsv-cities, SALAD and CliqueMining evaluation code):

1. every database and query image is mapped to an L2-normalised global descriptor;
2. for each query, the ``k`` nearest database descriptors are retrieved with an *exact* faiss search;
3. a database image is a *positive* of a query when their geotags are within ``radius`` metres
   (25 m for Pittsburgh and MSLS), inside the query's region (city) when the split has regions: on a
   split, positives come from ``split.positives()`` (:mod:`vpr_nb.split`; :func:`positives_within` is the
   radius search underneath);
4. Recall@N is the fraction of queries for which at least one of the first N retrievals is a positive.

By default queries that have no positive at all are excluded from Recall@N and a warning says how
many (the MSLS convention); ``no_positive="all"`` counts them as misses over all queries (the
convention of pytorch-NetVlad, gmberton's benchmark and GSV-Cities); a split carries its dataset's
convention (``split.recall_convention``), which :func:`evaluate_on_split` and :func:`evaluate_model` use.
"""
from __future__ import annotations

import warnings
from typing import Iterable, Sequence

import faiss
import numpy as np
import torch
from ._checks import as_float_matrix, check_int
from ._threads import single_threaded_call
from .image_tensors import as_image_array, images_to_tensor
from .split import Split, check_split, positives_within

def _is_half(x) -> bool:
    """Whether ``x`` holds half-precision floats (torch bfloat16 / float16, numpy float16)."""
    dtype = getattr(x, "dtype", None)
    return dtype in (torch.bfloat16, torch.float16) or dtype == np.float16


def _half_names(**inputs) -> str:
    """``"bfloat16 descriptors (db_desc, q_desc)"``: the precision of the half-precision inputs, by name."""
    by: dict[str, list[str]] = {}
    for name, x in inputs.items():
        if _is_half(x):
            by.setdefault(str(x.dtype).removeprefix("torch."), []).append(name)
    return " and ".join(f"{dtype} descriptors ({', '.join(names)})" for dtype, names in by.items())


@single_threaded_call   # faiss's BLAS and OpenMP loops on one thread (vpr_nb._threads)
def retrieve(db_desc, q_desc, k: int) -> tuple[np.ndarray, np.ndarray]:
    """Exact k-nearest-neighbour search of each query descriptor among the database descriptors.

    Descriptors are expected to be L2-normalised (as every aggregator in :mod:`vpr_nb` returns).
    The search runs on ``faiss.IndexFlatIP``; the returned distances are the **squared Euclidean
    distances** ``||q - d||^2 = 2 - 2 <q, d>`` (exact for unit vectors), sorted ascending, so that the
    first column is the best match. Ranking is identical to ``faiss.IndexFlatL2`` on unit vectors.

    Half-precision descriptors (bfloat16 from autocast, float16) are searched in float32, with a
    UserWarning naming their precision: their rows are unit up to their rounding (1e-2) and are
    re-normalised after the conversion. Float32 descriptors are searched as they are.

    Returns ``(distances, indices)`` as float32 / int64 arrays of shape (num_queries, k).
    """
    half = _is_half(db_desc) or _is_half(q_desc)
    db = as_float_matrix(db_desc, "db_desc")
    q = as_float_matrix(q_desc, "q_desc", dim=db.shape[1])
    k = check_int(k, "k", minimum=1)
    if k > db.shape[0]:
        raise ValueError(f"k={k} is larger than the database ({db.shape[0]} descriptors); "
                         f"use k <= {db.shape[0]}")
    tol = 1e-2 if half else 1e-3
    norms, q_norms = np.linalg.norm(db, axis=1), np.linalg.norm(q, axis=1)
    if np.abs(norms - 1).max() > tol or np.abs(q_norms - 1).max() > tol:
        raise ValueError("descriptors must be L2-normalised (unit rows); "
                         "apply torch.nn.functional.normalize(x, dim=1) or faiss.normalize_L2 first")
    if half:
        warnings.warn(f"retrieve got {_half_names(db_desc=db_desc, q_desc=q_desc)}; upcast to float32 "
                      f"for the exact search and re-normalised (their rows are unit only to ~1e-2, so near ties may "
                      f"rank differently than in float32): pass float32 descriptors (e.g. x.float()) to search "
                      f"them as they are", stacklevel=3)
        db, q = db / norms[:, None], q / q_norms[:, None]
    index = faiss.IndexFlatIP(db.shape[1])
    index.add(db)
    sims, idx = index.search(q, k)
    dist = np.maximum(2.0 - 2.0 * sims, 0.0).astype(np.float32)
    return dist, idx.astype(np.int64)


def recall_at_n(predictions, positives: Sequence[Iterable[int]], ns: Sequence[int] = (1, 5, 10, 20),
                no_positive: str = "exclude", *, num_db: int | None = None) -> dict[int, float]:
    """Recall@N for each N in ``ns``: a query counts at N if any of its first N predictions is a positive.

    ``predictions`` is the (num_queries, k) index array from :func:`retrieve`; ``positives`` the list
    from :func:`positives_within`. Queries without any positive are, with ``no_positive="exclude"``
    (default, the MSLS convention), left out with a warning; with ``no_positive="all"`` they count as
    misses and the denominator is every query (pytorch-NetVlad, gmberton's benchmark, GSV-Cities).
    :func:`counted_queries` gives the denominator. Returns ``{N: recall}`` with recall in [0, 1].

    ``num_db``, the database size (give it whenever it is known): indices of ``predictions`` and
    ``positives`` must lie in ``0 .. num_db - 1`` (-1 in ``predictions``: no result, as faiss marks
    it), else ValueError; and an N larger than the database is answered with Recall@num_db (by then
    every database image is retrieved) and a warning naming those N. Without it each N needs N
    predictions per query.
    """
    if no_positive not in ("exclude", "all"):
        raise ValueError(f"no_positive must be 'exclude' or 'all', got {no_positive!r}")
    pred = np.asarray(predictions)
    if pred.ndim != 2 or not np.issubdtype(pred.dtype, np.integer):
        raise ValueError(f"predictions must be a 2-D integer array (num_queries, k), got shape "
                         f"{pred.shape} and dtype {pred.dtype}")
    if len(positives) != pred.shape[0]:
        raise ValueError(f"positives has {len(positives)} entries but predictions has {pred.shape[0]} rows; "
                         f"they must describe the same queries")
    ns = [check_int(n, "N in ns") for n in ns]
    if not ns:
        raise ValueError("ns is empty: give at least one N, e.g. ns=(1, 5, 10)")
    cut = {n: n for n in ns}
    if num_db is not None:
        num_db = check_int(num_db, "num_db")
        beyond = sorted({n for n in ns if n > num_db})
        if beyond:
            warnings.warn(f"Recall@N for N = {beyond} is larger than the database ({num_db} images): it equals "
                          f"Recall@{num_db}, which is reported for those N", stacklevel=2)
            cut = {n: min(n, num_db) for n in ns}
    need = max(cut.values())
    if need > pred.shape[1]:
        raise ValueError(f"N={need} needs at least {need} predictions per query, got {pred.shape[1]}; "
                         f"retrieve with k >= {need}")
    if pred.size and pred.min() < -1:
        raise ValueError(f"predictions hold the index {int(pred.min())}: database indices are 0 .. num_db - 1 "
                         f"(-1 marks a missing result)")
    if num_db is not None and pred.size and pred.max() >= num_db:
        row = int(np.flatnonzero((pred >= num_db).any(axis=1))[0])
        raise ValueError(f"predictions hold the index {int(pred.max())} (first in query row {row}) but the "
                         f"database has {num_db} images (indices 0 .. {num_db - 1}): predictions of another "
                         f"database?")
    has_pos = np.array([len(p) > 0 for p in positives])
    if not has_pos.any():
        raise ValueError("no query has a positive: check the radius and that database and queries overlap")
    if not has_pos.all() and no_positive == "exclude":
        warnings.warn(f"{int((~has_pos).sum())} of {len(positives)} queries have no positive within the "
                      f"radius and are excluded from Recall@N", stacklevel=2)
    # Vectorised membership test: encode (query, db index) pairs as one int64 key each.
    lengths = np.array([len(p) for p in positives], dtype=np.int64)
    pos_flat = np.concatenate([np.asarray(p, dtype=np.int64).ravel() for p in positives])
    if pos_flat.size and (pos_flat.min() < 0 or (num_db is not None and pos_flat.max() >= num_db)):
        bad = int(pos_flat.min() if pos_flat.min() < 0 else pos_flat.max())
        raise ValueError(f"positives hold the database index {bad}, outside 0 .. "
                         f"{'num_db - 1' if num_db is None else num_db - 1}")
    width = int(max(pred.max(initial=0), pos_flat.max(initial=0))) + 1
    pos_keys = np.repeat(np.arange(len(positives), dtype=np.int64), lengths) * width + pos_flat
    pred_keys = np.arange(pred.shape[0], dtype=np.int64)[:, None] * width + pred
    hits = np.isin(pred_keys, pos_keys) & (pred >= 0)
    # first rank at which a positive appears (k if none)
    first = np.where(hits.any(axis=1), hits.argmax(axis=1), pred.shape[1])
    if no_positive == "exclude":
        first = first[has_pos]
    return {n: float(np.mean(first < cut[n])) for n in ns}


def counted_queries(positives: Sequence[Iterable[int]], no_positive: str = "exclude") -> int:
    """The number of queries :func:`recall_at_n` divides by under the convention ``no_positive``."""
    if no_positive not in ("exclude", "all"):
        raise ValueError(f"no_positive must be 'exclude' or 'all', got {no_positive!r}")
    return len(positives) if no_positive == "all" else sum(1 for p in positives if len(p) > 0)


@torch.no_grad()
def compute_descriptors(model: torch.nn.Module, images, batch_size: int = 256, device=None) -> np.ndarray:
    """Run ``model`` in eval mode over uint8 images (N, H, W, 3) and return float32 descriptors (N, D).

    The model's training/eval mode is restored afterwards.
    """
    batch_size = check_int(batch_size, "batch_size")
    arr = as_image_array(images)
    if len(arr.shape) != 4 or arr.shape[0] == 0:
        raise ValueError(f"images must be a non-empty (N, H, W, 3) array, got shape {arr.shape}")
    if device is None:
        device = next(model.parameters()).device
    was_training = model.training
    model.eval()
    out = []
    try:
        for start in range(0, arr.shape[0], batch_size):
            x = images_to_tensor(arr[start:start + batch_size]).to(device)
            out.append(model(x).float().cpu())
    finally:
        model.train(was_training)
    return torch.cat(out).numpy().astype(np.float32)


def raw_pixel_descriptors(images) -> np.ndarray:
    """The simplest global descriptor: the flattened image (pixels scaled to [0, 1]), L2-normalised."""
    arr = np.asarray(images)
    if arr.ndim != 4 or arr.shape[0] == 0:
        raise ValueError(f"images must be a non-empty (N, H, W, C) array, got shape {arr.shape}")
    x = arr.reshape(arr.shape[0], -1).astype(np.float32) / 255.0
    norms = np.linalg.norm(x, axis=1, keepdims=True)
    return x / np.maximum(norms, 1e-12)


def _recall(db_desc, q_desc, positives, ns: Sequence[int], no_positive: str) -> dict[int, float]:
    db = as_float_matrix(db_desc, "db_desc")
    k = min(max(ns, default=1), db.shape[0])
    _, idx = retrieve(db_desc, q_desc, k)
    return recall_at_n(idx, positives, ns, no_positive=no_positive, num_db=db.shape[0])


def evaluate_descriptors(db_desc, q_desc, db_utm, q_utm, radius: float,
                         ns: Sequence[int] = (1, 5, 10, 20), no_positive: str = "exclude") -> dict[int, float]:
    """Positives + retrieval + Recall@N in one call from raw geotags (:func:`positives_within`, no
    regions); ``no_positive`` as in :func:`recall_at_n`. On a split, :func:`evaluate_on_split`."""
    return _recall(db_desc, q_desc, positives_within(db_utm, q_utm, radius), ns, no_positive)


def evaluate_on_split(db_desc, q_desc, split: Split, ns: Sequence[int] = (1, 5, 10, 20),
                      no_positive: str | None = None) -> dict[int, float]:
    """Recall@N of descriptors of ``split``'s database and queries: positives from ``split.positives()``
    (per region when the split has regions), convention ``no_positive`` or, by default, the split's
    ``recall_convention``."""
    check_split(split)
    return _recall(db_desc, q_desc, split.positives(), ns, no_positive or split.recall_convention)


def evaluate_model(model: torch.nn.Module, split: Split, ns: Sequence[int] = (1, 5, 10, 20),
                   batch_size: int = 256, no_positive: str | None = None) -> dict[int, float]:
    """Recall@N of ``model`` on a :class:`~vpr_nb.split.Split` (:func:`evaluate_on_split`)."""
    check_split(split)
    db = compute_descriptors(model, split.db_images, batch_size)
    q = compute_descriptors(model, split.q_images, batch_size)
    return evaluate_on_split(db, q, split, ns, no_positive)


def mean_pairwise_cosine(descriptors) -> float:
    """Mean cosine similarity over all pairs of distinct rows of L2-normalised ``descriptors`` (N ≥ 2).

    Uses ``‖Σ dᵢ‖² = N + Σ_{i≠j} dᵢ·dⱼ``, so it costs O(N·D). Close to 1: every image gets nearly the
    same descriptor (a collapsed embedding); a healthy VPR embedding sits far below.
    """
    d = np.asarray(descriptors, dtype=np.float64)
    if d.ndim != 2 or len(d) < 2:
        raise ValueError(f"descriptors must be an (N >= 2, D) array, got shape {d.shape}")
    n = len(d)
    s = d.sum(axis=0)
    return float((s @ s - (d * d).sum()) / (n * (n - 1)))


def recall_row(db_desc, q_desc, split: Split, ns: Sequence[int] = (1, 5, 10)) -> dict:
    """One row of a results table: Recall@N on ``split`` (:func:`evaluate_on_split`, 4 decimals), the
    descriptor dimension and the mean pairwise cosine of the database descriptors (training health,
    notebook 02)."""
    rec = evaluate_on_split(db_desc, q_desc, split, ns)
    db = as_float_matrix(db_desc, "db_desc")
    return {**{f"R@{n}": round(float(rec[n]), 4) for n in ns}, "dim": int(db.shape[1]),
            "mean cosine": round(mean_pairwise_cosine(db), 4)}


def model_recall_row(model: torch.nn.Module, split, ns: Sequence[int] = (1, 5, 10)) -> dict:
    """:func:`recall_row` of ``model``'s descriptors on ``split``."""
    return recall_row(compute_descriptors(model, split.db_images), compute_descriptors(model, split.q_images), split, ns)
