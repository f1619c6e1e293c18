"""The ``"city"`` world (Pittsburgh-like): a street grid lined with buildings.

Database images every ``place_spacing`` metres along every street, in ``headings`` directions per
place, all in the reference condition; queries at random street positions with viewpoint jitter and
another condition. Positives: within ``pos_radius`` (25 m). Splits are bands along x.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from ..cameras import Cameras, split_bands
from ..layout import (MIN_WALL_ALBEDO, WALL, Scene, SegmentStore, facade_styles, finish_scene, rgb,
                      tree_segments)
from .base import WorldKind

# Rendering constants (the scene knobs are WorldConfig fields).
FACADE_PHASE = 50.0                # a facade's texture starts at a random offset in [0, 50) m
QUERY_JITTER_PER_AXIS = 0.7        # std per axis = 0.7 x position_jitter: a radial rms of ~position_jitter
SIDEWALK_WIDTH = 3.0               # ground: sidewalk along the blocks, inside the street's half width
LANE_MARKING_HALF_WIDTH = 0.15     # ground: dashed centre line of each street between intersections
DASH_PERIOD, DASH_LENGTH = 6, 3    # (dashes along x + y, in metres)
ROAD_COLOUR, SIDEWALK_COLOUR, MARKING_COLOUR = rgb(0.30, 0.30, 0.32), rgb(0.62, 0.60, 0.56), rgb(0.9, 0.9, 0.8)


def _street_trees(cfg, rng: np.random.Generator, length: float, half: float) -> tuple[np.ndarray, np.ndarray]:
    """(position along the street, offset across it) of the trees of one street of ``length`` m."""
    t = np.arange(cfg.street_tree_start, length, cfg.street_tree_spacing) + rng.uniform(-cfg.street_tree_shift,
                                                                                        cfg.street_tree_shift)
    keep = rng.random(len(t)) < cfg.street_tree_share
    side = np.where(rng.random(len(t)) < 0.5, -1, 1) * (half - cfg.street_tree_inset)
    return t[keep], side[keep]


def layout(cfg, rng: np.random.Generator) -> Scene:
    """Buildings of random width and height along every block side (blocks of ``block_size`` between
    streets of ``street_width``), and trees on some sidewalks."""
    styles = facade_styles(cfg, rng)
    bx, by = cfg.blocks
    pitch = cfg.block_size + cfg.street_width
    half = cfg.street_width / 2
    store = SegmentStore()
    ring = cfg.outer_blocks
    for i in range(-ring, bx + ring):
        for j in range(-ring, by + ring):
            x0, y0 = i * pitch + half, j * pitch + half
            x1, y1 = x0 + cfg.block_size, y0 + cfg.block_size
            corners = [(x0, y0), (x1, y0), (x1, y1), (x0, y1)]
            for c in range(4):
                p, q = np.array(corners[c]), np.array(corners[(c + 1) % 4])
                length = np.linalg.norm(q - p)
                cuts = [0.0]
                while cuts[-1] < length - cfg.corner_remainder:
                    cuts.append(min(length, cuts[-1] + rng.uniform(*cfg.building_width)))
                cuts[-1] = length
                cuts = np.array(cuts)
                nb = len(cuts) - 1
                t0, t1 = cuts[:-1] / length, cuts[1:] / length
                a = p + (q - p) * t0[:, None]
                b = p + (q - p) * t1[:, None]
                st = rng.integers(0, cfg.num_facade_types, nb)
                col = np.clip(styles[st, :3] + rng.normal(0, cfg.colour_variation, (nb, 3)), MIN_WALL_ALBEDO, 1)
                h = rng.uniform(*cfg.building_height, nb)
                store.add(a, b, np.zeros(nb), h, np.full(nb, WALL), st, col, rng.uniform(0, FACADE_PHASE, nb))
    L_x, L_y = bx * pitch, by * pitch
    tree_pos = []
    for y in np.arange(by + 1) * pitch:
        t, side = _street_trees(cfg, rng, L_x, half)
        tree_pos.append(np.stack([t, y + side], 1))
    for x in np.arange(bx + 1) * pitch:
        t, side = _street_trees(cfg, rng, L_y, half)
        tree_pos.append(np.stack([x + side, t], 1))
    tree_pos = np.concatenate(tree_pos)
    # no trees in intersections
    near = (np.abs(((tree_pos[:, 0] + pitch / 2) % pitch) - pitch / 2) < half) & \
           (np.abs(((tree_pos[:, 1] + pitch / 2) % pitch) - pitch / 2) < half)
    tree_segments(store, tree_pos[~near], cfg, rng)
    return finish_scene(store, cfg, rng, CITY, center=np.array([L_x / 2, L_y / 2]),
                        layout=dict(pitch=pitch, half=half), styles=styles)


def cameras(cfg, rng: np.random.Generator, scene: Scene) -> Cameras:
    """Database cameras at every place along the streets in ``headings`` street-relative directions;
    queries at random places, moved along the street, jittered, kept off the sidewalks."""
    bx, by = cfg.blocks
    pitch = cfg.block_size + cfg.street_width
    L_x, L_y = bx * pitch, by * pitch
    places, street_dir = [], []
    for y in np.arange(by + 1) * pitch:
        t = np.arange(cfg.place_spacing / 2, L_x, cfg.place_spacing)
        places.append(np.stack([t, np.full_like(t, y)], 1))
        street_dir.append(np.zeros(len(t)))
    for x in np.arange(bx + 1) * pitch:
        t = np.arange(cfg.place_spacing / 2, L_y, cfg.place_spacing)
        places.append(np.stack([np.full_like(t, x), t], 1))
        street_dir.append(np.full(len(t), 90.0))
    places, street_dir = np.concatenate(places), np.concatenate(street_dir)
    P, nh = len(places), cfg.headings
    hs = cfg.heading_offset + np.arange(nh) * 360.0 / nh
    db_pos = np.repeat(places, nh, 0) + rng.normal(0, cfg.db_position_jitter, (P * nh, 2))
    db_head = (np.repeat(street_dir, nh) + np.tile(hs, P) + rng.normal(0, cfg.db_heading_jitter, P * nh)) % 360
    db_place = np.repeat(np.arange(P), nh)
    # queries: random places, a random offset along the street, a random database heading + jitter
    nq = int(round(cfg.queries_per_place * P))
    qp = rng.integers(0, P, nq)
    along = rng.uniform(-cfg.place_spacing / 2, cfg.place_spacing / 2, nq)
    sd = np.radians(street_dir[qp])
    q_pos = places[qp] + np.stack([np.cos(sd), np.sin(sd)], 1) * along[:, None]
    q_pos = q_pos + rng.normal(0, cfg.position_jitter, (nq, 2)) * QUERY_JITTER_PER_AXIS
    # keep queries on the street (clamp the cross-street offset)
    cross = np.stack([-np.sin(sd), np.cos(sd)], 1)
    off = ((q_pos - places[qp]) * cross).sum(1)
    lim = cfg.street_width / 2 - cfg.kerb_margin
    q_pos -= cross * (off - np.clip(off, -cfg.street_width / 2 + cfg.kerb_margin, lim))[:, None]
    q_head = (street_dir[qp] + hs[rng.integers(0, nh, nq)] + rng.normal(0, cfg.heading_jitter, nq)) % 360
    gap = cfg.pos_radius * cfg.split_gap
    return Cameras(db_pos=db_pos, db_heading=db_head, db_place=db_place,
                   db_split=split_bands(db_pos[:, 0], 0, L_x, cfg.split_fractions, gap=gap),
                   q_pos=q_pos, q_heading=q_head, q_place=cKDTree(places).query(q_pos)[1],
                   q_split=split_bands(q_pos[:, 0], 0, L_x, cfg.split_fractions, gap=gap), q_tag=q_pos)


def ground(gp: np.ndarray, plan: dict, snow: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """City ground colour at points ``gp`` (P, 2): streets every ``pitch`` m along x and y (``half``:
    half the street width) with asphalt between the sidewalks and a dashed centre line between the
    intersections; paving on the sidewalks and inside the blocks. Snow lies everywhere."""
    pitch, half = plan["pitch"], plan["half"]
    ox = np.abs(((gp[:, 0] + pitch / 2) % pitch) - pitch / 2)   # distance to the nearest street's centre line
    oy = np.abs(((gp[:, 1] + pitch / 2) % pitch) - pitch / 2)
    road = (ox < half - SIDEWALK_WIDTH) | (oy < half - SIDEWALK_WIDTH)
    marking = ((ox < LANE_MARKING_HALF_WIDTH) & (oy > half)) | ((oy < LANE_MARKING_HALF_WIDTH) & (ox > half))
    gcol = np.where(road[:, None], ROAD_COLOUR, SIDEWALK_COLOUR)
    return np.where((marking & ((gp.sum(1) % DASH_PERIOD) < DASH_LENGTH))[:, None], MARKING_COLOUR, gcol), snow


CITY = WorldKind(
    name="city", description=__doc__.splitlines()[0], layout=layout, cameras=cameras, ground=ground,
    skyline_colour=rgb(0.42, 0.45, 0.52),
    fields=frozenset({"blocks", "block_size", "street_width", "place_spacing", "headings", "heading_offset",
                      "queries_per_place", "outer_blocks", "building_width", "building_height", "corner_remainder",
                      "street_tree_start", "street_tree_spacing", "street_tree_shift", "street_tree_share",
                      "street_tree_inset", "db_position_jitter", "db_heading_jitter", "kerb_margin"}),
    sizes={"tiny": {}, "small": {"blocks": (20, 6)}},
)
