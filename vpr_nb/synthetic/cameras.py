"""Cameras: where every database and query image is taken, its geotag, place group and split.

A world kind places its cameras (:mod:`vpr_nb.synthetic.kinds`) and returns a :class:`Cameras`; the
splits are geographically disjoint bands along one axis (:func:`split_bands`), separated by a gap of
``split_gap`` x ``pos_radius`` so that no query has a positive in another split. What a query looks
like besides its pose, its condition, horizon shift and occluders, is drawn by :func:`query_draws`.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class Cameras:
    """Poses (positions in m, headings in degrees), place groups and split indices (-1: in a gap) of the
    database and query cameras. ``q_tag`` is the query geotag: where the query stands, or (route) its
    frame's position on the track."""

    db_pos: np.ndarray
    db_heading: np.ndarray
    db_place: np.ndarray
    db_split: np.ndarray
    q_pos: np.ndarray
    q_heading: np.ndarray
    q_place: np.ndarray
    q_split: np.ndarray
    q_tag: np.ndarray


def split_bands(coord: np.ndarray, lo: float, hi: float, fractions, gap: float) -> np.ndarray:
    """Split index (0/1/2) of each coordinate along one axis; -1 inside the gaps between splits."""
    edges = lo + (hi - lo) * np.cumsum([0, *fractions])
    out = np.full(len(coord), -1)
    for k in range(3):
        a = edges[k] + (gap / 2 if k > 0 else -1e9)
        b = edges[k + 1] - (gap / 2 if k < 2 else -1e9)
        out[(coord >= a) & (coord < b)] = k
    return out


def query_draws(cfg, n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(condition index into ``cfg.query_conditions``, horizon shift in pixels, number of occluders)
    of ``n`` queries."""
    cond = rng.integers(0, len(cfg.query_conditions), n)
    pitch = rng.normal(0, cfg.pitch_jitter, n)
    occluders = rng.poisson(cfg.occluder_rate, n)
    return cond, pitch, occluders
