"""A real :class:`~vpr_nb.datasets.GeoSplit` as the :class:`vpr_nb.split.Split` that training and evaluation read.

:class:`TrainingSplit` adds the images (lazy :class:`~vpr_nb.datasets.ImageArray` of a fixed size, read
only when indexed) to a loader's listing and takes everything else from it, so
:class:`vpr_nb.training.TripletSource`, the samplers and :func:`vpr_nb.evaluation.evaluate_model` read
it as they read the synthetic world's splits.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..split import SIDES, Split
from .images import ImageArray
from .registry import recall_convention
from .split import PER_IMAGE, GeoSplit

# radii used when the format defines none (GSV-Cities): the NetVLAD / MSLS 25 m and 10 m
_FALLBACK_POS_RADIUS = 25.0
_FALLBACK_TRAIN_POS_RADIUS = 10.0


@dataclass(eq=False)
class TrainingSplit(Split):
    """The :class:`~vpr_nb.split.Split` of a :class:`GeoSplit`: ``*_images`` are lazy :class:`ImageArray` of
    ``image_size`` (H, W) over ``*_paths`` (``q_images`` None without queries); the geotags, headings,
    places and regions are the GeoSplit's; ``recall_convention`` is the format's (:func:`recall_convention`).
    Where the format defines no radius (GSV-Cities) ``pos_radius`` is 25 m and ``train_pos_radius`` 10 m
    (NetVLAD's)."""

    geo: GeoSplit
    image_size: tuple[int, int]

    def __post_init__(self):
        if not isinstance(self.geo, GeoSplit):
            raise ValueError(f"geo must be a GeoSplit (from vpr_nb.datasets.load), got {type(self.geo).__name__}")
        g = self.geo
        for side in SIDES:
            paths = list(getattr(g, f"{side}_paths"))
            setattr(self, f"{side}_paths", paths)
            setattr(self, f"{side}_images", ImageArray(paths, self.image_size) if paths else None)
            for extra in ("utm",) + PER_IMAGE:
                setattr(self, f"{side}_{extra}", getattr(g, f"{side}_{extra}"))
        self.pos_radius = g.pos_radius if g.pos_radius is not None else _FALLBACK_POS_RADIUS
        self.train_pos_radius = g.train_pos_radius if g.train_pos_radius is not None else _FALLBACK_TRAIN_POS_RADIUS
        self.recall_convention = recall_convention(g.format)
        self.name = g.name

    def _pool_images(self, sides: list[str], keep: np.ndarray) -> ImageArray:
        paths = [p for s in sides for p in getattr(self, f"{s}_paths")]
        return ImageArray([p for p, k in zip(paths, keep) if k], self.db_images.size)


__all__ = ["TrainingSplit"]
