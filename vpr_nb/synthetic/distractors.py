"""Distractors: parked cars and pedestrians, boxes in 3-D that differ between visits of a place.

Real places are full of content that does not identify them: the cars parked along a street and the people
on its pavement change from one day to the next. With ``distractor_rate`` > 0 (a
:class:`~vpr_nb.synthetic.config.WorldConfig` field, 0 = none: then nothing here runs and no random number
is drawn) every *visit* gets its own distractors:

* a **visit** is a set of cameras that see the same moment: the database cameras of one place
  (``db_place``: the headings of a city place, a route's frame group) or one query;
* its distractors stand within ``VISIT_RANGE`` metres (along the street or track) of the visit's cameras'
  mean position, ``distractor_rate`` per ``RATE_LENGTH`` metres on average (both sides together), never
  nearer than ``CLEARANCE`` to one of its cameras. City: cars (a share ``car_share``) parked on the road at
  the kerb, along the street, and pedestrians on the pavement; route: both beside the track;
* each is a box of four vertical faces in world coordinates, drawn by the ray caster like any other segment
  (:func:`extend_scene`): with depth, occlusion, parallax, sun shading and fog, so it moves with the
  viewpoint. A camera sees only its own visit's boxes, and only their faces towards it (one hit per ray);
* a visit's boxes come from its own random stream, ``default_rng([seed, DISTRACTOR_SEED, side, visit])``:
  independent of the other visits and of which splits are rendered, and different between two visits of
  the same place (the database and a query, two queries).

The constants below are rendering constants (sizes, colours, placement margins), not scene knobs.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from .kinds.city import SIDEWALK_WIDTH
from .layout import DISTRACTOR, Scene

DISTRACTOR_SEED = 104729           # the visits' random streams: default_rng([seed, DISTRACTOR_SEED, side, visit])
RATE_LENGTH = 10.0                 # distractor_rate counts distractors per 10 m of street or track
VISIT_RANGE = 30.0                 # a visit's distractors stand within +-30 m (along) of its cameras' centre ...
CLEARANCE = 1.5                    # ... their centre >= 1.5 m + half their length from each of its cameras
CAR_SIZE = ((3.8, 4.8), (1.6, 1.9), (1.3, 1.7))          # (length, width, height) ranges (m)
PEDESTRIAN_SIZE = ((0.4, 0.6), (0.25, 0.4), (1.5, 1.9))
KERB_GAP = 0.2                     # city: cars park 0.2 m from the kerb, on the road
PAVEMENT_MARGIN = 0.5              # city: pedestrians keep 0.5 m from the kerb and from the facades
TRACK_DISTANCE = (2.5, 8.0)        # route: a distractor's centre is this far from the track
CAR_YAW_JITTER = 0.05              # cars turn up to +-0.05 rad off the street (pedestrians: any direction)
ALBEDO = (0.05, 0.9)               # colour channels drawn uniformly in this range


@dataclass
class Distractors:
    """The distractor boxes of a set of cameras, as vertical faces standing on the ground, four per box.

    Faces run counter-clockwise around their box, so a face's outward normal is on its right. ``face_visit``
    says whose visit a face belongs to, ``camera_visit`` the visit of each camera (one row per camera)."""

    a: np.ndarray              # (F, 2) face start (m)
    b: np.ndarray              # (F, 2) face end (m)
    z1: np.ndarray             # (F,) top height (m)
    colour: np.ndarray         # (F, 3) rgb in [0, 1]
    face_visit: np.ndarray     # (F,) visit id of each face
    camera_visit: np.ndarray   # (N,) visit id of each camera

    def take(self, idx) -> "Distractors":
        """The same boxes for the cameras ``idx`` (an index array or mask into the cameras)."""
        return dataclasses.replace(self, camera_visit=self.camera_visit[idx])


class Extension(NamedTuple):
    """A scene with per-camera segments appended (``scene``) and the (N, E) table of the appended segments
    each camera may see, as indices into ``scene`` (-1 = padding), for the ray caster."""

    scene: Scene
    cand: np.ndarray


def _street_frame(plan: dict, anchor: np.ndarray) -> tuple[np.ndarray, float]:
    """City: the point of the nearest street's centre line next to ``anchor`` and the street's angle (rad)."""
    pitch = plan["pitch"]
    nearest = np.round(anchor / pitch) * pitch
    off = np.abs(anchor - nearest)                       # to the nearest street along y (x), along x (y)
    if off[1] <= off[0]:                                 # on a street along x
        return np.array([anchor[0], nearest[1]]), 0.0
    return np.array([nearest[0], anchor[1]]), np.pi / 2


def _in_intersection(plan: dict, p: np.ndarray) -> np.ndarray:
    """City: whether points ``p`` (k, 2) lie where two streets cross."""
    pitch, half = plan["pitch"], plan["half"]
    o = np.abs(((p + pitch / 2) % pitch) - pitch / 2)
    return (o[:, 0] < half) & (o[:, 1] < half)


def _track_frame(plan: dict, anchor: np.ndarray, along: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Route: the track's points (k, 2) and headings (k,) ``along`` metres from the track point nearest
    ``anchor`` (arc length, clipped to the track's ends)."""
    track, heading = plan["track"], plan["heading"]
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(track, axis=0), axis=1))])
    s = arc[np.argmin(((track - anchor) ** 2).sum(1))] + along
    pts = np.stack([np.interp(s, arc, track[:, 0]), np.interp(s, arc, track[:, 1])], 1)
    return pts, np.interp(s, arc, heading)


def _visit_boxes(cfg, plan: dict, cams: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, ...]:
    """(centres (k, 2), yaws (k,), sizes (k, 3), colours (k, 3)) of one visit's boxes; ``cams`` (c, 2) are
    the visit's camera positions."""
    anchor = cams.mean(0)
    count = rng.poisson(cfg.distractor_rate * 2 * VISIT_RANGE / RATE_LENGTH)
    along = rng.uniform(-VISIT_RANGE, VISIT_RANGE, count)
    side = np.where(rng.random(count) < 0.5, -1.0, 1.0)
    car = rng.random(count) < cfg.car_share
    car_size, pedestrian_size = np.array(CAR_SIZE), np.array(PEDESTRIAN_SIZE)           # (3, 2): (low, high)
    lo = np.where(car[:, None], car_size[:, 0], pedestrian_size[:, 0])
    hi = np.where(car[:, None], car_size[:, 1], pedestrian_size[:, 1])
    size = lo + (hi - lo) * rng.random((count, 3))                       # length, width, height
    size[:, 2] *= cfg.distractor_height_scale
    colour = rng.uniform(*ALBEDO, (count, 3))
    turn = np.where(car, CAR_YAW_JITTER, np.pi) * rng.uniform(-1, 1, count)
    spread = rng.random(count)
    if "pitch" in plan:                                                  # the city's street grid
        origin, angle = _street_frame(plan, anchor)
        d, n = np.array([np.cos(angle), np.sin(angle)]), np.array([-np.sin(angle), np.cos(angle)])
        kerb = plan["half"] - SIDEWALK_WIDTH
        lateral = np.where(car, kerb - KERB_GAP - size[:, 1] / 2,
                           kerb + PAVEMENT_MARGIN + spread * (SIDEWALK_WIDTH - 2 * PAVEMENT_MARGIN))
        centre = origin + along[:, None] * d + (side * lateral)[:, None] * n
        yaw = angle + turn
        keep = ~_in_intersection(plan, centre)
    elif "track" in plan:                                                # the route's track
        pts, head = _track_frame(plan, anchor, along)
        n = np.stack([-np.sin(head), np.cos(head)], 1)
        lateral = TRACK_DISTANCE[0] + spread * (TRACK_DISTANCE[1] - TRACK_DISTANCE[0])
        centre = pts + (side * lateral)[:, None] * n
        yaw = head + turn
        keep = np.ones(count, dtype=bool)
    else:
        raise ValueError(f"distractors know the city's streets and the route's track, not world kind {cfg.preset!r}")
    gap = np.sqrt(((centre[:, None, :] - cams[None, :, :]) ** 2).sum(-1)).min(1) if count else np.zeros(0)
    keep &= gap >= CLEARANCE + size[:, 0] / 2
    return centre[keep], yaw[keep], size[keep], colour[keep]


def _box_faces(centre: np.ndarray, yaw: np.ndarray, size: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Faces (a, b), each (4k, 2), of k boxes, box-major, counter-clockwise around each box."""
    d = np.stack([np.cos(yaw), np.sin(yaw)], 1) * size[:, :1] / 2
    n = np.stack([-np.sin(yaw), np.cos(yaw)], 1) * size[:, 1:2] / 2
    corners = np.stack([centre - d - n, centre + d - n, centre + d + n, centre - d + n], 1)     # (k, 4, 2)
    return corners.reshape(-1, 2), np.roll(corners, -1, axis=1).reshape(-1, 2)


def place_distractors(cfg, scene: Scene, cam_pos: np.ndarray, camera_visit: np.ndarray, seed: int,
                      side: int) -> Distractors:
    """The distractors of cameras at ``cam_pos`` (N, 2) grouped into visits by ``camera_visit`` (N,
    non-negative ints); ``seed`` (the world's) and ``side`` (0 database, 1 queries) pick the random streams."""
    cam_pos = np.asarray(cam_pos, dtype=float)
    camera_visit = np.asarray(camera_visit, dtype=np.int64)
    if cam_pos.ndim != 2 or cam_pos.shape[1] != 2 or camera_visit.shape != (len(cam_pos),):
        raise ValueError(f"cam_pos must be (N, 2) and camera_visit (N,), got {cam_pos.shape} and {camera_visit.shape}")
    if len(camera_visit) and camera_visit.min() < 0:
        raise ValueError("camera_visit must hold non-negative visit ids")
    visits, inverse = np.unique(camera_visit, return_inverse=True)
    order = np.argsort(inverse, kind="stable")
    groups = np.split(order, np.cumsum(np.bincount(inverse, minlength=len(visits)))[:-1])
    parts = []
    for v, members in zip(visits, groups):
        rng = np.random.default_rng([int(seed), DISTRACTOR_SEED, int(side), int(v)])
        parts.append((v, *_visit_boxes(cfg, scene.layout, cam_pos[members], rng)))
    centre = np.concatenate([p[1] for p in parts]) if parts else np.zeros((0, 2))
    yaw = np.concatenate([p[2] for p in parts]) if parts else np.zeros(0)
    size = np.concatenate([p[3] for p in parts]) if parts else np.zeros((0, 3))
    colour = np.concatenate([p[4] for p in parts]) if parts else np.zeros((0, 3))
    box_visit = np.concatenate([np.full(len(p[1]), p[0], dtype=np.int64) for p in parts]) if parts else \
        np.zeros(0, np.int64)
    a, b = _box_faces(centre, yaw, size)
    return Distractors(a=a, b=b, z1=np.repeat(size[:, 2], 4), colour=np.repeat(colour, 4, axis=0),
                       face_visit=np.repeat(box_visit, 4), camera_visit=camera_visit)


def extend_scene(scene: Scene, distractors: Distractors, pos: np.ndarray) -> Extension | None:
    """``scene`` with the faces of the visits of cameras at ``pos`` (N, 2) appended (material
    :data:`~vpr_nb.synthetic.layout.DISTRACTOR`, no texture), and the faces each camera sees: its own
    visit's faces that face it (back faces culled, so a ray meets one face per box). None when no camera
    sees one: the scene is then drawn as without distractors."""
    keep = np.isin(distractors.face_visit, distractors.camera_visit)
    a, b, z1, colour, visit = (x[keep] for x in (distractors.a, distractors.b, distractors.z1, distractors.colour,
                                                  distractors.face_visit))
    e = b - a
    outward = np.stack([e[:, 1], -e[:, 0]], 1)
    towards = ((pos[:, None, :] - (a + b)[None] / 2) * outward[None]).sum(-1) > 0              # (N, F)
    sees = towards & (visit[None, :] == distractors.camera_visit[:, None])
    width = int(sees.sum(1).max()) if sees.size else 0
    if width == 0:
        return None
    order = np.argsort(~sees, axis=1, kind="stable")[:, :width]
    cand = np.where(np.take_along_axis(sees, order, 1), len(scene.a) + order, -1)
    f = len(a)
    grown = dataclasses.replace(
        scene, a=np.concatenate([scene.a, a]), b=np.concatenate([scene.b, b]),
        z0=np.concatenate([scene.z0, np.zeros(f)]), z1=np.concatenate([scene.z1, z1]),
        kind=np.concatenate([scene.kind, np.full(f, DISTRACTOR, dtype=scene.kind.dtype)]),
        style=np.concatenate([scene.style, np.zeros(f, dtype=scene.style.dtype)]),
        colour=np.concatenate([scene.colour, colour]), u0=np.concatenate([scene.u0, np.zeros(f)]))
    return Extension(scene=grown, cand=cand)
