"""The one split type that training and evaluation read, :class:`Split`, and its positives search.

A split is a database and a query side of geotagged images. Every split of the package is a
:class:`Split`: the synthetic world's :class:`vpr_nb.synthetic.VPRDataset` (images in memory) and a
real dataset's :class:`vpr_nb.datasets.TrainingSplit` (images read lazily from disk). The training
sources, the samplers, the per-epoch validation, :func:`vpr_nb.evaluation.evaluate_model` and both
reproduction commands read only the attributes and methods declared here, so they treat both alike.

Positives (NetVLAD / gmberton / SALAD evaluation): database image ``j`` is a positive of query ``i``
when ``||utm_q[i] - utm_db[j]||_2 <= radius`` (:func:`positives_within`, a k-d tree range search). When
a split carries region labels (MSLS and GSV-Cities cities) the search runs inside each region only
(:func:`region_positives`): UTM coordinates of different cities are not comparable, so regions are what
keeps cities apart, for positives as for the samplers.
"""
from __future__ import annotations

import dataclasses
from typing import NamedTuple

import numpy as np
from scipy.spatial import cKDTree

from ._checks import as_utm, check_positive

SIDES = ("db", "q")   # database, queries: the prefixes of every per-image attribute


def positives_within(db_utm, q_utm, radius: float) -> list[np.ndarray]:
    """Database indices within ``radius`` metres of each query (inclusive), sorted ascending.

    Uses a KD-tree range search, so memory is O(number of positives), never an N×M matrix.

    Returns a list with one int64 array per query (possibly empty).
    """
    db = as_utm(db_utm, "db_utm")
    q = as_utm(q_utm, "q_utm")
    radius = check_positive(radius, "radius", allow_zero=True)
    tree = cKDTree(db)
    hits = tree.query_ball_point(q, r=radius, return_sorted=True)
    return [np.asarray(h, dtype=np.int64) for h in hits]


def region_positives(db_utm, q_utm, radius: float | None, db_region=None, q_region=None, *,
                     name: str = "this split") -> list[np.ndarray]:
    """Database indices within ``radius`` metres of each query (sorted, int64), per region when both
    ``db_region`` and ``q_region`` are given (one label per image), else over the whole split; a query
    whose region has no database image gets none.

    ``name`` only labels the error messages: a split without queries (a training-only set such as
    GSV-Cities) or without a radius (``radius=None``) raises ValueError saying what to pass.
    """
    if len(q_utm) == 0:
        raise ValueError(f"{name} has no queries (a training-only set); positives need queries")
    if radius is None:
        raise ValueError(f"{name} defines no positives radius; pass radius=... in metres")
    if db_region is None or q_region is None:
        return positives_within(db_utm, q_utm, radius)
    db_utm, q_utm = np.asarray(db_utm), np.asarray(q_utm)
    db_region, q_region = np.asarray(db_region), np.asarray(q_region)
    if len(db_region) != len(db_utm) or len(q_region) != len(q_utm):
        raise ValueError(f"{name}: db_region/q_region have {len(db_region)}/{len(q_region)} labels but there are "
                         f"{len(db_utm)}/{len(q_utm)} database/query images; give one region per image")
    out: list[np.ndarray] = [np.zeros(0, np.int64)] * len(q_utm)
    for reg in np.unique(q_region):
        qi = np.flatnonzero(q_region == reg)
        di = np.flatnonzero(db_region == reg)
        if len(di) == 0:
            continue
        for i, hit in zip(qi, positives_within(db_utm[di], q_utm[qi], radius)):
            out[i] = di[hit]
    return out


class PlacePool(NamedTuple):
    """The images of a split that carry a place id (database first, then queries), for place batches:
    ``images`` (an indexable image array), ``places`` (int64 place ids, all >= 0), ``utm`` (N, 2) and
    ``regions`` (one city label per image, or None for one region)."""

    images: object
    places: np.ndarray
    utm: np.ndarray
    regions: np.ndarray | None


class Split:
    """The split type: what every consumer of a split may read.

    Per side (``db_`` for the database, ``q_`` for the queries), one entry per image:

    - ``*_images``: uint8 ``(N, H, W, 3)``, a numpy array or a lazy on-disk
      :class:`vpr_nb.datasets.ImageArray` (``q_images`` is None for a set without queries);
    - ``*_utm``: float64 ``(N, 2)`` easting/northing in metres;
    - ``*_heading``: camera headings in degrees, or None;
    - ``*_place``: place ids (MSLS ``unique_cluster``, GSV-Cities place; -1 = none), or None when the
      data has no places;
    - ``*_region``: city labels, or None (one region); no positive, negative or clique crosses a region;
    - ``*_paths``: the image files, or None for images held in memory;

    and ``name``, ``pos_radius`` (evaluation positives, metres), ``train_pos_radius`` (training
    positives, metres) and ``recall_convention`` (``"exclude"``: queries without a positive are left out
    of Recall@N; ``"all"``: they count as misses; see :func:`vpr_nb.evaluation.recall_at_n`).
    Regions and paths default to None and the convention to ``"exclude"`` (the synthetic world's);
    a subclass sets everything else (None where the data has no headings or places).
    """

    name: str
    db_images: object
    q_images: object
    db_utm: np.ndarray
    q_utm: np.ndarray
    pos_radius: float
    train_pos_radius: float
    db_heading: np.ndarray | None
    q_heading: np.ndarray | None
    db_place: np.ndarray | None
    q_place: np.ndarray | None
    # defaults for what the synthetic world does not have (class attributes, not dataclass fields)
    db_region: np.ndarray | None = None
    q_region: np.ndarray | None = None
    db_paths: list | None = None
    q_paths: list | None = None
    recall_convention: str = "exclude"

    @property
    def has_queries(self) -> bool:
        return self.q_images is not None and len(self.q_utm) > 0

    @property
    def has_places(self) -> bool:
        return self.db_place is not None

    def take_queries(self, index) -> "Split":
        """A copy of this split with only the queries at ``index`` (an index array or a boolean mask): every
        per-query field (``q_*``) is taken at ``index``, those that are None stay None, and the database is
        shared. For a split type that is a dataclass (the synthetic world's, the real datasets')."""
        if not dataclasses.is_dataclass(self):
            raise ValueError(f"take_queries needs a dataclass split, got {type(self).__name__}")
        index = np.asarray(index)
        if index.dtype == bool:
            index = np.flatnonzero(index)
        if index.ndim != 1 or not np.issubdtype(index.dtype, np.integer):
            raise ValueError(f"index must be a 1-D array of query indices or a boolean mask, got {index.dtype} "
                             f"with shape {index.shape}")
        n = len(self.q_utm)
        if len(index) and (index.min() < -n or index.max() >= n):
            raise ValueError(f"index holds query indices outside 0..{n - 1}")

        def take(value):
            if value is None:
                return None
            return [value[i] for i in index] if isinstance(value, list) else value[index]
        return dataclasses.replace(self, **{f.name: take(getattr(self, f.name)) for f in dataclasses.fields(self)
                                            if f.name.startswith("q_")})

    def positives(self, radius: float | None = None) -> list[np.ndarray]:
        """Database indices within ``radius`` (default ``pos_radius``) of each query, sorted, per region
        when the split has regions (:func:`region_positives`)."""
        return region_positives(self.db_utm, self.q_utm, self.pos_radius if radius is None else radius,
                                self.db_region, self.q_region, name=self.name)

    def image_names(self, side: str) -> list[str]:
        """One name per image of ``side`` (``"db"`` or ``"q"``): its path, or ``"<side>_<index>"`` for
        images held in memory."""
        if side not in SIDES:
            raise ValueError(f"side must be 'db' or 'q', got {side!r}")
        paths = getattr(self, f"{side}_paths")
        if paths is not None:
            return [str(p) for p in paths]
        return [f"{side}_{i}" for i in range(len(getattr(self, f"{side}_utm")))]

    def place_pool(self) -> PlacePool:
        """The images with a place id, database first, then the queries when they have place ids too."""
        if not self.has_places:
            raise ValueError(f"{self.name} has no place ids; place batches need them (GSV-Cities, MSLS or the "
                             "synthetic world), or use triplets")
        sides = ["db"] + (["q"] if self.has_queries and self.q_place is not None else [])
        places = np.concatenate([np.asarray(getattr(self, f"{s}_place"), dtype=np.int64) for s in sides])
        keep = places >= 0
        if not keep.any():
            raise ValueError(f"{self.name}: no image has a place id (all are -1)")
        utm = np.concatenate([np.asarray(getattr(self, f"{s}_utm"), dtype=np.float64) for s in sides])
        labelled = all(getattr(self, f"{s}_region") is not None for s in sides)
        regions = np.concatenate([np.asarray(getattr(self, f"{s}_region")) for s in sides]) if labelled else None
        images = self._pool_images(sides, keep)
        return PlacePool(images, places[keep], utm[keep], None if regions is None else regions[keep])

    def _pool_images(self, sides: list[str], keep: np.ndarray):
        """The images of ``sides`` (concatenated) where ``keep``; in-memory arrays here (TrainingSplit
        keeps them on disk)."""
        images = np.concatenate([getattr(self, f"{s}_images") for s in sides]) if len(sides) > 1 else self.db_images
        return images if keep.all() else images[keep]


def check_split(split, what: str = "split") -> Split:
    """``split`` itself when it is a :class:`Split`, else ValueError saying which objects are."""
    if not isinstance(split, Split):
        raise ValueError(f"{what} must be a vpr_nb.split.Split (a split of vpr_nb.synthetic.make_dataset, e.g. "
                         f"ds.train, or a vpr_nb.datasets.TrainingSplit), got {type(split).__name__}")
    return split


__all__ = ["Split", "PlacePool", "check_split", "positives_within", "region_positives", "SIDES"]
