"""The ``"route"`` world (Nordland-like): one long railway through countryside.

Trees, houses, catenary poles and fences along a smooth curvy track, in landscape zones (forest,
field, village) that change slowly, and roadside objects close to the track (more content per metre:
``roadside_spacing``, one per metre per side by default; 0 leaves them out); a camera turned ``camera_yaw``
degrees (45 by default; 0 looks forward) to the side takes one frame every ``frame_spacing`` metres; the
database is summer, the queries winter, frame-aligned. Positives: the same frame +-1
(``pos_radius = 1.01 * frame_spacing``). Splits are bands of frames.

**Route density** (``camera_spacing`` in metres; 0, the default, is off): the scene is laid out as always, on
``num_frames`` track points ``frame_spacing`` metres apart (the same draws, so the same track, trees, houses,
...), but the cameras take one frame every ``camera_spacing`` metres along that same track,
``floor((num_frames - 1) * frame_spacing / camera_spacing) + 1`` frames in all (:func:`route_frames`). The
query jitters scale with the spacing: position and heading jitter are ``position_jitter`` and
``heading_jitter`` times ``camera_spacing / frame_spacing`` (a query strays as far, in frames, as at the
layout's spacing), and the positive radius is ``1.01 * camera_spacing`` (frames i-1, i, i+1).
``frames_per_group`` counts camera frames. A denser route has more frames per metre of the same world, so a
model's wrong top-1 falls more often a few frames from the right one (a near miss, what CliqueMining's batches
are made of; notebook 07). With ``camera_spacing=0`` (the default) every draw and every pixel is today's;
``camera_spacing == frame_spacing`` gives the same frames too.
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np
from scipy.spatial import cKDTree

from ..cameras import Cameras, split_bands
from ..layout import (FENCE, MIN_WALL_ALBEDO, POLE, WALL, Scene, SegmentStore, facade_styles, finish_scene, rgb,
                      tree_segments)
from ..hashing import hash01
from .base import WorldKind

TRACK_PAD = 200                    # curvature noise is drawn for num_frames + 200 frames, then smoothed
# Rendering constants (the scene knobs are WorldConfig fields).
HOUSE_PHASE = 20.0                 # a house wall's texture starts at a random offset in [0, 20) m
POLE_HALF_WIDTH = 0.15             # a pole is two crossed quads 0.3 m wide ...
POLE_CROSS_OFFSET = 0.01           # ... the second one 1 cm further from the track
POLE_COLOUR, FENCE_COLOUR = rgb(0.3, 0.3, 0.3), rgb(0.55, 0.4, 0.25)
RAIL_SAMPLES = 20                  # the rails' distance field: the track sampled 20 times per frame
TRACK_HALF_WIDTH = 1.6             # ground: ballast bed on each side of the track's centre line
RAIL_BAND = (0.7, 0.9)             # ground: the rails, at these distances from the centre line
SNOW_FREE_TRACK = 1.0              # ground: no snow this close to the centre line
GRASS_PATCH = 4                    # ground: grass brightness varies per 4 m x 4 m patch
SIGN_SHARE, SIGN_BOTTOM = 0.3, 0.6  # roadside objects: 30 % are signs hanging from 0.6 x their top
ROADSIDE_ALBEDO = (0.05, 0.95)     # their colour channels are drawn uniformly in this range
BALLAST_COLOUR, RAIL_COLOUR, GRASS_COLOUR = rgb(0.38, 0.34, 0.30), rgb(0.6, 0.6, 0.62), rgb(0.25, 0.42, 0.18)


class RouteFrames(NamedTuple):
    """Where the route's cameras stand: one frame every ``spacing`` metres along the track, ``count`` frames,
    the query jitters multiplied by ``jitter_scale`` (``camera_spacing / frame_spacing``; 1 when off)."""

    spacing: float
    count: int
    jitter_scale: float


def route_frames(cfg) -> RouteFrames:
    """The camera frames of a route config: every ``frame_spacing`` m (``num_frames`` of them) when
    ``camera_spacing`` is 0, else every ``camera_spacing`` m along the same track (module docstring)."""
    if not cfg.camera_spacing > 0:
        return RouteFrames(float(cfg.frame_spacing), int(cfg.num_frames), 1.0)
    length = (cfg.num_frames - 1) * cfg.frame_spacing
    count = int(np.floor(length / cfg.camera_spacing + 1e-9)) + 1
    return RouteFrames(float(cfg.camera_spacing), count, cfg.camera_spacing / cfg.frame_spacing)


def _check(cfg) -> None:
    if cfg.track_smoothing > TRACK_PAD:
        raise ValueError(f"track_smoothing must be <= {TRACK_PAD} frames, got {cfg.track_smoothing}")
    if cfg.camera_spacing > 0:
        spacing, count, _ = route_frames(cfg)
        gap = int(np.ceil(cfg.pos_radius * cfg.split_gap / spacing))
        split = split_bands(np.arange(count, dtype=float), 0, count, cfg.split_fractions, gap=gap)
        empty = [k for k in range(3) if not (split == k).any()]
        if empty:
            length = (cfg.num_frames - 1) * cfg.frame_spacing
            raise ValueError(f"camera_spacing={cfg.camera_spacing} m does not fit the track: its "
                             f"{length:g} m (num_frames={cfg.num_frames} x frame_spacing={cfg.frame_spacing} m) "
                             f"hold {count} frame(s), too few for three splits (split(s) {empty} would be empty); "
                             f"use a smaller camera_spacing or a longer track (num_frames)")


def _track(cfg, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """A smooth curvy track: positions every frame_spacing m and the forward heading (rad)."""
    n, w = cfg.num_frames, cfg.track_smoothing
    curv = np.convolve(rng.normal(0, 1, n + TRACK_PAD), np.ones(w) / w, mode="same")[TRACK_PAD // 2:TRACK_PAD // 2 + n]
    heading = np.cumsum(curv * cfg.track_curvature * cfg.frame_spacing / 5.0)
    step = cfg.frame_spacing * np.stack([np.cos(heading), np.sin(heading)], 1)
    pos = np.concatenate([[np.zeros(2)], np.cumsum(step, 0)[:-1]])
    return pos, heading


def layout(cfg, rng: np.random.Generator) -> Scene:
    """The track, then along it: trees (by zone density), houses (boxes of four walls), catenary poles
    on one side, fences in the fields and, when ``roadside_spacing`` > 0, roadside objects."""
    track, heading = _track(cfg, rng)
    styles = facade_styles(cfg, rng)
    store = SegmentStore()
    n = len(track)
    normal = np.stack([-np.sin(heading), np.cos(heading)], 1)
    fwd = np.stack([np.cos(heading), np.sin(heading)], 1)
    zone = np.repeat(rng.integers(0, len(cfg.zone_tree_density), n // cfg.zone_frames + 2), cfg.zone_frames)[:n]
    trees = []
    for side in (-1, 1):
        for k in range(n):
            m = rng.poisson(cfg.zone_tree_density[zone[k]] * cfg.trees_per_frame)
            if m:
                off = side * rng.uniform(*cfg.tree_distance, m)
                along = rng.uniform(0, cfg.frame_spacing, m)
                trees.append(track[k] + fwd[k] * along[:, None] + normal[k] * off[:, None])
    tree_segments(store, np.concatenate(trees), cfg, rng)
    for k in range(0, n, cfg.house_every):
        if rng.random() < cfg.zone_house_share[zone[k]]:
            side = rng.choice([-1, 1])
            c = track[k] + normal[k] * side * rng.uniform(*cfg.house_distance)
            w, d = rng.uniform(*cfg.house_width), rng.uniform(*cfg.house_depth)
            ang = heading[k] + rng.uniform(-cfg.house_yaw, cfg.house_yaw)
            R = np.array([[np.cos(ang), -np.sin(ang)], [np.sin(ang), np.cos(ang)]])
            corners = (np.array([[-w, -d], [w, -d], [w, d], [-w, d]]) / 2) @ R.T + c
            st = rng.integers(0, cfg.num_facade_types)
            col = np.clip(styles[st, :3] + rng.normal(0, cfg.colour_variation, 3), MIN_WALL_ALBEDO, 1)
            h = rng.uniform(*cfg.house_height)
            for e in range(4):
                store.add(corners[e][None], corners[(e + 1) % 4][None], [0.0], [h], [WALL], [st], col[None],
                          [rng.uniform(0, HOUSE_PHASE)])
    for k in range(0, n, max(1, int(cfg.pole_spacing / cfg.frame_spacing))):
        p = track[k] + normal[k] * cfg.pole_offset
        for axis in (fwd[k], normal[k]):       # two crossed quads, the second a hair further out
            store.add((p - axis * POLE_HALF_WIDTH)[None], (p + axis * POLE_HALF_WIDTH)[None], [0.0],
                      [cfg.pole_height], [POLE], [0], POLE_COLOUR[None], [0.0])
            p = p + normal[k] * POLE_CROSS_OFFSET
    e = cfg.fence_every
    for k in range(0, n - e, e):
        share = cfg.zone_fence_share[zone[k]]
        if share > 0 and rng.random() < share:
            side = rng.choice([-1, 1])
            p, q = track[k] + normal[k] * side * cfg.fence_offset, track[k + e] + normal[k + e] * side * cfg.fence_offset
            store.add(p[None], q[None], [0.0], [cfg.fence_height], [FENCE], [0], FENCE_COLOUR[None], [0.0])
    if cfg.roadside_spacing > 0:
        _roadside(store, cfg, rng, track, heading, normal, fwd)
    # the rails: a KD-tree over the track sampled RAIL_SAMPLES times per frame (distance to the polyline)
    fine = np.concatenate([track[:-1] + (track[1:] - track[:-1]) * f
                           for f in np.linspace(0, 1, RAIL_SAMPLES, endpoint=False)])
    return finish_scene(store, cfg, rng, ROUTE, center=track.mean(0),
                        layout=dict(track=track, heading=heading, track_tree=cKDTree(fine)), styles=styles)


def _roadside(store: SegmentStore, cfg, rng: np.random.Generator, track, heading, normal, fwd) -> None:
    """Roadside objects on both sides of the track, one per ``roadside_spacing`` metres per side on
    average (Poisson count, uniform positions): flat panels (posts, boards, bins, signs) of random
    colour, ``roadside_width`` wide and ``roadside_height`` tall, turned up to +-90 degrees off the
    track, ``roadside_distance`` from it; a share of them are signs that hang above the ground. They
    are near the camera, so a few metres of travel moves them far across the image (parallax), and
    their colours do not change with the season."""
    n = len(track)
    for side in (-1, 1):
        m = rng.poisson(n * cfg.frame_spacing / cfg.roadside_spacing)
        k = rng.integers(0, n, m)
        c = (track[k] + fwd[k] * rng.uniform(0, cfg.frame_spacing, m)[:, None]
             + normal[k] * (side * rng.uniform(*cfg.roadside_distance, m))[:, None])
        ang = heading[k] + rng.uniform(-np.pi / 2, np.pi / 2, m)
        half = np.stack([np.cos(ang), np.sin(ang)], 1) * (rng.uniform(*cfg.roadside_width, m) / 2)[:, None]
        top = rng.uniform(*cfg.roadside_height, m)
        bottom = np.where(rng.random(m) < SIGN_SHARE, top * SIGN_BOTTOM, 0.0)
        colour = rng.uniform(*ROADSIDE_ALBEDO, (m, 3))
        store.add(c - half, c + half, bottom, top, np.full(m, POLE), np.zeros(m), colour, np.zeros(m))


def _along_track(track: np.ndarray, heading: np.ndarray, frame_spacing: float, frames: RouteFrames):
    """Positions and headings (rad) every ``frames.spacing`` m along the track polyline (point k to k+1 runs
    ``frame_spacing`` m along ``heading[k]``, :func:`_track`)."""
    arc = np.arange(frames.count) * frames.spacing
    k = np.minimum(np.floor(arc / frame_spacing + 1e-9).astype(int), len(track) - 1)
    off = np.maximum(arc - k * frame_spacing, 0.0)
    return track[k] + off[:, None] * np.stack([np.cos(heading[k]), np.sin(heading[k])], 1), heading[k]


def cameras(cfg, rng: np.random.Generator, scene: Scene) -> Cameras:
    """One database camera per frame, looking along the track (turned ``camera_yaw`` degrees to the
    left: a sideways view, in which near content moves across the image); its query jittered along
    the track and in heading. A query is tagged with its frame's track position (Nordland's ground truth is
    frame-aligned), so positives within 1.01 x the frame spacing are exactly frames i-1, i, i+1; the
    along-track jitter only moves the rendered camera. Frames stand every ``frame_spacing`` m on the
    track's points, or every ``camera_spacing`` m along it with the jitters scaled (:func:`route_frames`)."""
    frames_at = route_frames(cfg)
    track, heading = scene.layout["track"], scene.layout["heading"]
    if cfg.camera_spacing > 0:
        track, heading = _along_track(track, heading, cfg.frame_spacing, frames_at)
    n = len(track)
    frames = np.arange(n)
    db_pos = track.copy()
    db_head = (np.degrees(heading) + cfg.camera_yaw) % 360
    fwd = np.stack([np.cos(heading), np.sin(heading)], 1)
    q_pos = track + fwd * rng.normal(0, cfg.position_jitter * frames_at.jitter_scale, n)[:, None]
    q_head = (db_head + rng.normal(0, cfg.heading_jitter * frames_at.jitter_scale, n)) % 360
    gap_frames = int(np.ceil(cfg.pos_radius * cfg.split_gap / frames_at.spacing))
    split = split_bands(frames.astype(float), 0, n, cfg.split_fractions, gap=gap_frames)
    place = frames // cfg.frames_per_group
    return Cameras(db_pos=db_pos, db_heading=db_head, db_place=place, db_split=split, q_pos=q_pos,
                   q_heading=q_head, q_place=place.copy(), q_split=split.copy(), q_tag=db_pos.copy())


def ground(gp: np.ndarray, plan: dict, snow: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Route ground colour at points ``gp`` (P, 2): the track (ballast bed and two rails, from the
    distance to the track's centre line) through patchy grass. Returns (colour, snow cover): no snow
    on the track's middle."""
    dd, _ = plan["track_tree"].query(gp)
    track = dd < TRACK_HALF_WIDTH
    patch = hash01((gp[:, 0] / GRASS_PATCH).astype(int), (gp[:, 1] / GRASS_PATCH).astype(int))
    grass = GRASS_COLOUR * (0.85 + 0.3 * patch)[:, None]
    gcol = np.where(track[:, None], BALLAST_COLOUR, grass)
    gcol = np.where((track & (dd > RAIL_BAND[0]) & (dd < RAIL_BAND[1]))[:, None], RAIL_COLOUR, gcol)
    return gcol, snow * (~track | (dd > SNOW_FREE_TRACK))


ROUTE = WorldKind(
    name="route", description=__doc__.splitlines()[0], layout=layout, cameras=cameras, ground=ground,
    skyline_colour=rgb(0.30, 0.40, 0.42),
    fields=frozenset({"num_frames", "frame_spacing", "camera_spacing", "frames_per_group", "track_curvature",
                      "track_smoothing", "zone_frames", "zone_tree_density", "zone_house_share", "zone_fence_share",
                      "trees_per_frame", "tree_distance", "house_every", "house_distance", "house_width", "house_depth", "house_height",
                      "house_yaw", "pole_spacing", "pole_offset", "pole_height", "fence_every", "fence_offset",
                      "fence_height", "camera_yaw", "roadside_spacing", "roadside_distance",
                      "roadside_height", "roadside_width"}),
    preset=dict(db_condition="summer", query_conditions=("winter",), position_jitter=0.8, heading_jitter=2.0,
                occluder_rate=0.0, split_fractions=(0.6, 0.2, 0.2), skyline_height=(10.0, 130.0),
                skyline_blockiness=0.0,
                # content per metre (notebook 00): roadside objects every metre per side and a camera turned 45°
                # to the side, so that frames a few metres apart are not near-duplicates
                roadside_spacing=1.0, camera_yaw=45.0),
    sizes={"tiny": {}, "small": {"num_frames": 3000}},
    pos_radius_frames=1.01,
    check=_check,
)
