"""The dataset type of the synthetic world: :class:`VPRDataset`, a geotagged database/query set and its splits."""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np

from ..split import Split
from .config import SPLITS, WorldConfig


@dataclass
class VPRDataset(Split):
    """A geotagged database/query set, with the fields every notebook uses.

    Images are uint8 (N, H, W, 3); UTM positions float64 (N, 2) in metres; headings in degrees;
    conditions are indices into ``condition_names``; splits are indices into ``SPLITS``;
    ``*_place`` are place-group ids (the MSLS ``unique_cluster`` analogue used by CliqueMining);
    ``*_labels`` are uint8 (N, H, W) content labels per pixel (:data:`~vpr_nb.synthetic.labels.LABEL_NAMES`)
    when the world was made with ``make_dataset(..., labels=True)``, else None.
    """

    name: str
    config: WorldConfig
    seed: int
    db_images: np.ndarray
    q_images: np.ndarray
    db_utm: np.ndarray
    q_utm: np.ndarray
    db_heading: np.ndarray
    q_heading: np.ndarray
    db_condition: np.ndarray
    q_condition: np.ndarray
    db_split: np.ndarray
    q_split: np.ndarray
    db_place: np.ndarray
    q_place: np.ndarray
    condition_names: tuple[str, ...]
    pos_radius: float
    train_pos_radius: float
    split_name: str = "all"
    extra: dict = field(default_factory=dict)
    db_labels: np.ndarray | None = None
    q_labels: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.db_images) + len(self.q_images)

    def __repr__(self) -> str:
        h, w = self.db_images.shape[1:3]
        return (f"VPRDataset({self.name!r}, split={self.split_name!r}, db={len(self.db_images)}, "
                f"queries={len(self.q_images)}, images={h}x{w}, pos_radius={self.pos_radius:g} m)")

    def split(self, name: str) -> "VPRDataset":
        """The subset of database and query images that belong to split ``name``."""
        if name not in SPLITS:
            raise ValueError(f"unknown split {name!r}; choose one of {SPLITS}")
        s = SPLITS.index(name)
        dm, qm = self.db_split == s, self.q_split == s
        if not dm.any() or not qm.any():
            raise ValueError(f"split {name!r} is empty in this dataset (it was generated with "
                             f"splits={self.extra.get('rendered_splits')})")
        fields = {}
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            if v is None:
                pass
            elif f.name.startswith("db_"):
                v = v[dm]
            elif f.name.startswith("q_"):
                v = v[qm]
            fields[f.name] = v
        fields["split_name"] = name
        return VPRDataset(**fields)

    @property
    def train(self) -> "VPRDataset":
        return self.split("train")

    @property
    def val(self) -> "VPRDataset":
        return self.split("val")

    @property
    def test(self) -> "VPRDataset":
        return self.split("test")
