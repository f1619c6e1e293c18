"""A real :class:`~vpr_nb.datasets.GeoSplit` in the shape the training loop and evaluation use.

:class:`TrainingSplit` gives an on-disk split the attributes of the synthetic
:class:`vpr_nb.synthetic.VPRDataset` splits (``db_images``/``q_images`` as lazy
:class:`~vpr_nb.datasets.ImageArray`, ``db_utm``, ``pos_radius``, ``positives()``...), so that
:class:`vpr_nb.training.TripletSource` and :func:`vpr_nb.evaluation.evaluate_model` read both alike.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .images import ImageArray
from .positives import region_positives
from .registry import recall_convention
from .split import GeoSplit

# radii used when the format defines none (GSV-Cities): the NetVLAD / MSLS 25 m and 10 m
_FALLBACK_POS_RADIUS = 25.0
_FALLBACK_TRAIN_POS_RADIUS = 10.0


@dataclass
class TrainingSplit:
    """A :class:`GeoSplit` seen through the attributes of the synthetic ``VPRDataset`` splits
    (``db_images``/``q_images`` as lazy :class:`ImageArray`, ``db_utm``, ``pos_radius``, ...), so
    :class:`vpr_nb.training.TripletSource` and :func:`vpr_nb.evaluation.evaluate_model` accept it.
    ``recall_convention`` is the format's (:func:`recall_convention`). Where the format defines no
    radius (GSV-Cities) ``pos_radius`` is 25 m and ``train_pos_radius`` 10 m (NetVLAD's)."""

    geo: GeoSplit
    image_size: tuple[int, int]

    def __post_init__(self):
        if not isinstance(self.geo, GeoSplit):
            raise ValueError(f"geo must be a GeoSplit (from vpr_nb.datasets.load), got {type(self.geo).__name__}")
        g = self.geo
        self.db_images = ImageArray(g.db_paths, self.image_size)
        self.q_images = ImageArray(g.q_paths, self.image_size) if g.q_paths else None
        self.db_utm, self.q_utm = g.db_utm, g.q_utm
        self.db_heading, self.q_heading = g.db_heading, g.q_heading
        self.db_place, self.q_place = g.db_place, g.q_place
        self.db_region, self.q_region = g.db_region, g.q_region
        self.pos_radius = g.pos_radius if g.pos_radius is not None else _FALLBACK_POS_RADIUS
        self.train_pos_radius = g.train_pos_radius if g.train_pos_radius is not None else _FALLBACK_TRAIN_POS_RADIUS
        self.recall_convention = recall_convention(g.format)
        self.name = g.name

    def positives(self, radius: float | None = None) -> list[np.ndarray]:
        """Database indices within ``radius`` (default ``pos_radius``) of each query, per region when
        the split has regions (MSLS cities): :func:`~vpr_nb.datasets.positives.region_positives`."""
        return region_positives(self.db_utm, self.q_utm, self.pos_radius if radius is None else radius,
                                self.db_region, self.q_region, name=self.name)


__all__ = ["TrainingSplit"]
