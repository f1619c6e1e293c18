"""The listing every real-format loader returns, :class:`GeoSplit`, and the operations on it.

A :class:`GeoSplit` is the common denominator of the VPR benchmarks read by :mod:`vpr_nb.datasets`
(Pittsburgh, gmberton's layout, MSLS, GSV-Cities, Nordland): image paths plus UTM geotags of a
database and a query side, the evaluation positives radius and optional per-image heading, place and
region. :func:`drop_images` filters it (e.g. after :func:`~vpr_nb.datasets.find_unreadable_images`).
It holds no images: :class:`~vpr_nb.datasets.TrainingSplit` turns it into the :class:`vpr_nb.split.Split`
that training and evaluation read.
"""
from __future__ import annotations

import os
from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

from ..split import SIDES, region_positives
from .images import ImageDataset

# the optional per-image fields (besides paths and utm) of both sides, ``db_<field>`` / ``q_<field>``
PER_IMAGE = ("heading", "place", "region")


@dataclass(eq=False)
class GeoSplit:
    """A geotagged database/query split of a real dataset (images stay on disk).

    ``db_paths``/``q_paths`` are absolute image paths (str); ``db_utm``/``q_utm`` float64 (N, 2)
    (easting, northing) in metres; ``pos_radius`` is the evaluation positives radius (a database
    image is a positive of a query when ``||utm_q - utm_db|| <= pos_radius``) and
    ``train_pos_radius`` the training-positives radius, ``None`` where the format does not define
    one. Optional per-image fields are ``None`` when the format does not have them:
    ``*_heading`` (degrees), ``*_place`` (place / cluster id: GSV-Cities place, MSLS
    ``unique_cluster``, -1 = none) and ``*_region`` (city names: positives are only searched inside
    one region, because UTM coordinates of different zones are not comparable). ``extras`` holds
    the format-specific rest (Nordland frame indices, MSLS night/view direction, UTM zones...).
    """

    name: str
    format: str
    db_paths: list
    q_paths: list
    db_utm: np.ndarray
    q_utm: np.ndarray
    pos_radius: float | None
    train_pos_radius: float | None = None
    db_heading: np.ndarray | None = None
    q_heading: np.ndarray | None = None
    db_place: np.ndarray | None = None
    q_place: np.ndarray | None = None
    db_region: np.ndarray | None = None
    q_region: np.ndarray | None = None
    extras: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        if not len(self.db_paths):
            raise ValueError(f"{self.name}: the database is empty; a split needs at least one database image")
        for side in SIDES:
            paths = getattr(self, f"{side}_paths")
            n = len(paths)
            utm = np.asarray(getattr(self, f"{side}_utm"), dtype=np.float64).reshape(-1, 2)
            if utm.shape[0] != n:
                raise ValueError(f"{self.name}: {side}_utm has {utm.shape[0]} rows but {n} {side} paths")
            if not np.isfinite(utm).all():
                bad = int(np.flatnonzero(~np.isfinite(utm).all(axis=1))[0])
                raise ValueError(f"{self.name}: {side}_utm is NaN/inf for {paths[bad]}; every image needs a geotag")
            setattr(self, f"{side}_utm", utm)
            for extra in PER_IMAGE:
                v = getattr(self, f"{side}_{extra}")
                if v is not None and len(v) != n:
                    raise ValueError(f"{self.name}: {side}_{extra} has {len(v)} entries but {n} {side} paths")

    @property
    def num_db(self) -> int:
        return len(self.db_paths)

    @property
    def num_q(self) -> int:
        return len(self.q_paths)

    def __len__(self) -> int:
        return self.num_db + self.num_q

    def __repr__(self) -> str:
        r = "-" if self.pos_radius is None else f"{self.pos_radius:g} m"
        return (f"GeoSplit({self.name!r}, format={self.format!r}, db={self.num_db}, queries={self.num_q}, "
                f"pos_radius={r})")

    def positives(self, radius: float | None = None) -> list[np.ndarray]:
        """Database indices within ``radius`` (default ``pos_radius``) of each query, sorted.

        The radius search of NetVLAD / gmberton / SALAD evaluation (``||x_q - x_db||_2 <= r``), done
        per region when ``*_region`` is set (:func:`vpr_nb.split.region_positives`).
        """
        return region_positives(self.db_utm, self.q_utm, self.pos_radius if radius is None else radius,
                                self.db_region, self.q_region, name=self.name)

    def check_files(self) -> None:
        """Stat every listed image; raise FileNotFoundError naming the first missing one."""
        check_image_files(self.db_paths + self.q_paths, self.name)

    def image_dataset(self, which: str = "all", size=None) -> "ImageDataset":
        """An :class:`ImageDataset` over the database (``"db"``), queries (``"q"``) or both (``"all"``,
        database first, so index ``i >= num_db`` is query ``i - num_db`` as in pytorch-NetVlad)."""
        paths = {"db": self.db_paths, "q": self.q_paths, "all": self.db_paths + self.q_paths}
        if which not in paths:
            raise ValueError(f"which must be 'db', 'q' or 'all', got {which!r}")
        return ImageDataset(paths[which], size=size)


def check_image_files(paths: Sequence[str], what: str) -> None:
    """Stat every path; raise FileNotFoundError counting the missing ones and naming the first
    (``what`` says which dataset they belong to). One ``os.path.isfile`` per file, as every loader runs it."""
    missing = 0
    first = None
    for p in paths:
        if not os.path.isfile(p):
            missing += 1
            if first is None:
                first = p
    if missing:
        raise FileNotFoundError(f"{what}: {missing} listed image(s) are missing, first: {first} "
                                f"(fix the images folder, or pass check_files=False to skip this check)")


def drop_images(split: GeoSplit, bad) -> GeoSplit:
    """A copy of ``split`` without the images whose path is in ``bad`` (per-image arrays and the
    ``extras`` arrays of matching length are filtered alike)."""
    if not isinstance(split, GeoSplit):
        raise ValueError(f"split must be a GeoSplit, got {type(split).__name__}")
    bad = {str(p) for p in bad}
    keep = {side: np.array([p not in bad for p in getattr(split, f"{side}_paths")], dtype=bool)
            for side in SIDES}
    if keep["db"].all() and keep["q"].all():
        return split
    kw = {}
    for side in SIDES:
        k = keep[side]
        kw[f"{side}_paths"] = [p for p, ok in zip(getattr(split, f"{side}_paths"), k) if ok]
        kw[f"{side}_utm"] = split.__dict__[f"{side}_utm"][k]
        for extra in PER_IMAGE:
            v = getattr(split, f"{side}_{extra}")
            kw[f"{side}_{extra}"] = None if v is None else np.asarray(v)[k]
    extras = {}
    for key, v in split.extras.items():
        side = key.split("_", 1)[0]
        if side in keep and isinstance(v, np.ndarray) and len(v) == len(keep[side]):
            v = v[keep[side]]
        elif side in keep and isinstance(v, list) and len(v) == len(keep[side]):
            v = [x for x, ok in zip(v, keep[side]) if ok]
        extras[key] = v
    if not kw["db_paths"]:
        raise ValueError(f"{split.name}: every database image is unreadable")
    return GeoSplit(name=split.name, format=split.format, pos_radius=split.pos_radius,
                    train_pos_radius=split.train_pos_radius, extras=extras, **kw)


__all__ = ["GeoSplit", "drop_images", "check_image_files", "PER_IMAGE"]
