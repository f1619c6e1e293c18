"""The one region-aware positives search shared by every split type: real :class:`~vpr_nb.datasets.GeoSplit`
and :class:`~vpr_nb.datasets.TrainingSplit`, and the synthetic :class:`vpr_nb.synthetic.VPRDataset`.

Convention (NetVLAD / gmberton / SALAD evaluation): database image ``j`` is a positive of query ``i``
when ``||utm_q[i] - utm_db[j]||_2 <= radius``. When both sides carry a region label (MSLS and
GSV-Cities city names), the search runs inside each region only, because UTM coordinates of different
cities (different zones) are not comparable; a query whose region has no database image gets none.
"""
from __future__ import annotations

import numpy as np

from ..evaluation import positives_within


def region_positives(db_utm, q_utm, radius: float | None, db_region=None, q_region=None, *,
                     name: str = "this split") -> list[np.ndarray]:
    """Database indices within ``radius`` metres of each query (sorted, int64), per region when both
    ``db_region`` and ``q_region`` are given (one label per image), else over the whole split.

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


__all__ = ["region_positives"]
