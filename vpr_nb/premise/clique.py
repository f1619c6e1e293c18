"""CliqueMining's premise, measured: the share of *near misses* among a model's retrieval failures.

CliqueMining (Izquierdo & Civera, ECCV 2024; :mod:`vpr_nb.samplers.clique`) fills a batch with dense cliques
of visually similar places, so that the loss sees **negatives that look alike and lie close**: images a few
frames (metres) beyond the positive radius. Such batches help only if a model's mistakes are of that kind:
if its wrong top-1 retrievals land a few frames from the true place (near misses), hard close negatives
are what training lacks; if they land anywhere on the route, they are not. This module measures it:

- :func:`failure_distances`: for every query whose top-1 retrieval is wrong (no positive of the query, the
  split's positives as in :func:`vpr_nb.evaluation.recall_at_n`), how far the retrieved image lies from the
  true place: in metres (geotag to geotag) and in **frames along the track** (:func:`track_frames`);
- :func:`near_miss_share`: the share of those failures within ``k`` frames (``k = 2, 4``): the quantity
  CliqueMining exploits;
- :func:`failure_histogram`: the failures counted per distance bin (frames), for a plot.

Frame density is the switch: the route's ``camera_spacing`` (:mod:`vpr_nb.synthetic.kinds.route`) takes
frames closer together along the same track, and the failures move closer in frames (notebook 07).

Frames need a frame-aligned split: a database of one image per frame in track order (the synthetic route,
Nordland) and queries tagged at a frame's position. The frame spacing comes from the split
(:func:`frame_spacing_of`) or from ``frame_spacing=...`` in metres.
"""
from __future__ import annotations

from typing import NamedTuple, Sequence

import numpy as np
from scipy.spatial import cKDTree

from .._checks import as_float_matrix, as_utm, check_int, check_positive
from ..evaluation import retrieve
from ..split import Split, check_split
from ..synthetic.kinds.route import route_frames

NEAR = (2, 4)          # near misses: within 2 and within 4 frames of the true place
STEP_TOLERANCE = 0.02  # consecutive database frames lie frame_spacing apart to within 2 % (or a whole gap apart)


class FailureDistances(NamedTuple):
    """The failures of a top-1 retrieval on a split, one entry per failing query.

    ``query``: the failing queries' indices (into the split's queries); ``retrieved``: their top-1 database
    index; ``metres``: the distance between the retrieved image's geotag and the query's (its true place);
    ``frames``: the same distance along the track in frames (whole numbers, float64);
    ``num_queries``: the queries counted (the split's recall convention: with ``"exclude"``, the queries
    that have a positive); ``frame_spacing``: metres per frame. ``len(query) / num_queries`` = 1 - Recall@1.
    """

    query: np.ndarray
    retrieved: np.ndarray
    metres: np.ndarray
    frames: np.ndarray
    num_queries: int
    frame_spacing: float


class FailureHistogram(NamedTuple):
    """Failures per distance bin: ``counts[i]`` in frames ``[edges[i], edges[i + 1])``; the last edge is inf."""

    counts: np.ndarray
    edges: np.ndarray


def frame_spacing_of(split: Split) -> float:
    """Metres between consecutive frames of ``split``: the synthetic route's camera spacing
    (:func:`vpr_nb.synthetic.kinds.route.route_frames`: ``camera_spacing`` when set, else ``frame_spacing``)
    or a Nordland split's ``extras["frame_spacing_m"]``; ValueError for a split without frames."""
    check_split(split)
    cfg = getattr(split, "config", None)
    if getattr(cfg, "preset", None) == "route":
        return route_frames(cfg).spacing
    extras = getattr(split, "extras", None)
    if isinstance(extras, dict) and "frame_spacing_m" in extras:
        return check_positive(extras["frame_spacing_m"], "extras['frame_spacing_m']")
    raise ValueError(f"{getattr(split, 'name', 'this split')} is not a route of frames (a synthetic 'route' "
                     f"world or Nordland), so it has no frame spacing: pass frame_spacing=... in metres, or "
                     f"measure failures in metres on a route split")


def track_frames(split: Split, frame_spacing: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Each image's position along the track, in frames: ``(db_frame, q_frame)`` (int64).

    The database must be one image per frame in track order (the route's and Nordland's): consecutive
    database images lie one frame spacing apart, or a whole number of spacings across a gap between
    splits, always moving on along the track, so database image ``j`` stands at frame ``sum of the rounded
    steps before it``. A query stands
    at the frame of the database image at its geotag (route queries are tagged with their frame's
    position), which must lie within half a spacing. ``frame_spacing`` (metres) defaults to
    :func:`frame_spacing_of`.
    """
    check_split(split)
    spacing = frame_spacing_of(split) if frame_spacing is None else check_positive(frame_spacing, "frame_spacing")
    name = getattr(split, "name", "this split")
    if getattr(split, "db_region", None) is not None or getattr(split, "q_region", None) is not None:
        raise ValueError(f"{name} has regions (cities); frames along one track need a single route")
    db = as_utm(split.db_utm, "split.db_utm")
    q = as_utm(split.q_utm, "split.q_utm")
    if len(db) < 2:
        raise ValueError(f"{name} has {len(db)} database image(s); frames along a track need at least 2")
    steps = np.linalg.norm(np.diff(db, axis=0), axis=1) / spacing
    whole = np.rint(steps)
    bad = (whole < 1) | (np.abs(steps - whole) > STEP_TOLERANCE * np.maximum(whole, 1))
    # and onwards: image j + 2 lies farther from j than either step (a track that turned back would not)
    skip = np.linalg.norm(db[2:] - db[:-2], axis=1) / spacing
    bad[:-1] |= skip < np.maximum(whole[:-1], whole[1:]) + 0.5
    if bad.any():
        j = int(np.flatnonzero(bad)[0])
        raise ValueError(f"{name}: database images {j} and {j + 1} lie {steps[j] * spacing:.3g} m apart: the database "
                         f"must be one image per frame in track order (a route split), a whole number of frame "
                         f"spacings ({spacing:g} m) apart and moving on along the track, and frame_spacing its spacing")
    db_frame = np.concatenate([[0], np.cumsum(whole)]).astype(np.int64)
    dist, nearest = cKDTree(db).query(q)
    if len(q) and dist.max() > spacing / 2:
        i = int(np.argmax(dist))
        raise ValueError(f"{name}: query {i} is {dist[i]:.3g} m from every database frame (more than half the "
                         f"frame spacing, {spacing:g} m): queries must be tagged at a frame's position")
    return db_frame, db_frame[nearest].astype(np.int64)


def failure_distances(db_descriptors, q_descriptors, split: Split,
                      frame_spacing: float | None = None) -> FailureDistances:
    """How far each wrong top-1 retrieval lies from the true place, in metres and in frames along the track.

    ``db_descriptors`` / ``q_descriptors``: L2-normalised descriptors (one row per database / query image of
    ``split``, in its order, e.g. from :func:`vpr_nb.evaluation.compute_descriptors`), searched exactly with
    :func:`vpr_nb.evaluation.retrieve`. A query fails when its top-1 is none of its positives
    (``split.positives()``, within ``split.pos_radius``); queries without a positive are left out under the
    split's ``"exclude"`` convention and count as failures under ``"all"``, as in Recall@1.
    CliqueMining exploits the failures that lie a few frames away (:func:`near_miss_share`).
    """
    check_split(split)
    db = as_float_matrix(db_descriptors, "db_descriptors")
    q = as_float_matrix(q_descriptors, "q_descriptors", dim=db.shape[1])
    n_db, n_q = len(split.db_utm), len(split.q_utm)
    if len(db) != n_db or len(q) != n_q:
        raise ValueError(f"descriptors describe {len(db)} database / {len(q)} query images but the split has "
                         f"{n_db} / {n_q}: compute them on this split's db_images and q_images, in order")
    db_frame, q_frame = track_frames(split, frame_spacing)
    spacing = frame_spacing_of(split) if frame_spacing is None else float(frame_spacing)
    top = retrieve(db, q, 1)[1][:, 0]
    positives = split.positives()
    has = np.array([len(p) > 0 for p in positives])
    hit = np.array([bool(np.any(np.asarray(p) == t)) for p, t in zip(positives, top)])
    counted = has if split.recall_convention == "exclude" else np.ones(n_q, dtype=bool)
    fail = np.flatnonzero(counted & ~hit)
    ret = top[fail]
    metres = np.linalg.norm(np.asarray(split.db_utm, dtype=np.float64)[ret]
                            - np.asarray(split.q_utm, dtype=np.float64)[fail], axis=1)
    frames = np.abs(db_frame[ret] - q_frame[fail]).astype(np.float64)
    return FailureDistances(query=fail.astype(np.int64), retrieved=ret.astype(np.int64), metres=metres,
                            frames=frames, num_queries=int(counted.sum()), frame_spacing=spacing)


def _frames(distances_in_frames) -> np.ndarray:
    """The distances in frames of a :class:`FailureDistances` or an array, checked: 1-D, >= 0, no NaN."""
    x = distances_in_frames.frames if isinstance(distances_in_frames, FailureDistances) else distances_in_frames
    try:
        arr = np.asarray(x, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"distances_in_frames must be numbers (a 1-D array), got {type(x).__name__}") from None
    if arr.ndim != 1:
        raise ValueError(f"distances_in_frames must be a 1-D array (one distance per failure), got shape {arr.shape}")
    if np.isnan(arr).any() or (arr < 0).any():
        raise ValueError("distances_in_frames must be >= 0 and not NaN (frames between the retrieved image and "
                         "the true place, e.g. failure_distances(...).frames)")
    return arr


def near_miss_share(distances_in_frames, within: int | Sequence[int] = NEAR) -> dict[int, float]:
    """The share of failures within ``k`` frames of the true place, for each ``k`` in ``within``.

    ``distances_in_frames``: :attr:`FailureDistances.frames` (or the :class:`FailureDistances` itself), one
    distance per wrong top-1. Near misses (a wrong top-1 a few frames from the right one) are what
    CliqueMining's batches of close, look-alike places train against; a high share says its premise holds.
    Returns ``{k: share}``; NaN when there is no failure (no share to take).
    """
    frames = _frames(distances_in_frames)
    ks = [] if within is None else [within] if isinstance(within, (str, bytes)) or np.ndim(within) == 0 else list(within)
    if not ks:
        raise ValueError("within is empty: give one or more frame counts, e.g. within=(2, 4)")
    ks = [check_int(k, "within (frames)") for k in ks]
    if not len(frames):
        return {k: float("nan") for k in ks}
    return {k: float(np.mean(frames <= k)) for k in ks}


def failure_histogram(distances_in_frames, bins: int | Sequence[float] = 20) -> FailureHistogram:
    """Failures per distance bin (frames), for a bar plot of where a model's mistakes land.

    ``bins``: an int ``B`` gives one bin per frame, ``[0, 1), [1, 2), ..., [B, B + 1)``, then ``[B + 1, inf)``;
    a sequence gives increasing bin edges (the first <= every distance), then ``[last edge, inf)``.
    """
    frames = _frames(distances_in_frames)
    if isinstance(bins, (int, np.integer)) and not isinstance(bins, bool):
        edges = np.arange(check_int(bins, "bins", minimum=0) + 2, dtype=np.float64)
    else:
        try:
            edges = np.asarray(bins, dtype=np.float64)
        except (TypeError, ValueError):
            raise ValueError(f"bins must be an int or a sequence of bin edges, got {bins!r}") from None
        if edges.ndim != 1 or len(edges) < 1 or not np.isfinite(edges).all() or (np.diff(edges) <= 0).any():
            raise ValueError(f"bins must be finite, strictly increasing bin edges in frames, got {bins!r}")
    if len(frames) and frames.min() < edges[0]:
        raise ValueError(f"a distance of {frames.min():g} frames lies below the first bin edge {edges[0]:g}")
    edges = np.append(edges, np.inf)
    counts = np.histogram(frames, bins=edges)[0] if len(frames) else np.zeros(len(edges) - 1, np.int64)
    return FailureHistogram(counts=counts.astype(np.int64), edges=edges)


__all__ = ["FailureDistances", "FailureHistogram", "NEAR", "failure_distances", "failure_histogram",
           "frame_spacing_of", "near_miss_share", "track_frames"]
