"""A procedural visual-place-recognition world: the teaching dataset of every notebook.

``make_dataset(preset, seed)`` builds a small geotagged world and renders it with a 2.5-D ray caster
(numpy only, no downloads). Two presets mirror the two kinds of real benchmark:

``"city"`` (Pittsburgh-like)
    a street grid lined with buildings; database images every ``place_spacing`` metres along every
    street, in ``headings`` directions per place, all in the reference condition; queries at random
    street positions with viewpoint jitter and another condition. Positives: within 25 m.
``"route"`` (Nordland-like)
    one long railway through countryside (trees, houses, poles, fences, hills); a camera looking
    forward takes one frame every ``frame_spacing`` metres; the database is summer, the queries
    winter, frame-aligned. Positives: the same frame +-1 (``pos_radius = 1.01 * frame_spacing``).

What makes it VPR-shaped (and what the knobs of :class:`WorldConfig` control):

* **parallax layers** - a far skyline ring (almost no parallax), near facades / trees (strong parallax)
  and a textured ground plane, so nearby cameras share content and the view changes continuously
  with distance;
* **perceptual aliasing** - facades are drawn from a small library of ``num_facade_types`` styles, so
  distant places can look alike (``colour_variation`` sets how much individual buildings differ);
* **condition changes** - illumination and sun direction, season palettes (foliage, snow), fog,
  rain noise, lit windows at dusk (``condition_strength`` scales them all);
* **occluders** - passing cars and pedestrians drawn into query images (``occluder_rate``);
* **camera jitter** - position, heading and pitch noise of the query cameras.

Splits (train / val / test) are geographically disjoint bands separated by a gap wider than the
positive radius, so no query has a positive in another split.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Sequence

import numpy as np
from scipy.spatial import cKDTree

from ._checks import check_int
from .split import Split

SPLITS = ("train", "val", "test")

# ----------------------------------------------------------------------------------------------
# Conditions: each is a small set of rendering parameters. The database uses the first one.
# ----------------------------------------------------------------------------------------------
CONDITIONS = {
    #            brightness, tint (rgb),        sun azimuth/deg, ambient, sky rgb,            foliage,  snow, fog m, noise, lit windows
    "summer":   dict(bright=1.00, tint=(1.00, 1.00, 1.00), sun=135.0, ambient=0.55, sky=(0.55, 0.72, 0.95), foliage=(0.20, 0.50, 0.15), snow=0.0, fog=400.0, noise=0.015, lit=0.0),
    "overcast": dict(bright=0.80, tint=(0.95, 0.97, 1.02), sun=135.0, ambient=0.95, sky=(0.70, 0.72, 0.75), foliage=(0.22, 0.42, 0.18), snow=0.0, fog=120.0, noise=0.03, lit=0.0),
    "dusk":     dict(bright=0.50, tint=(1.25, 0.85, 0.65), sun=290.0, ambient=0.45, sky=(0.95, 0.55, 0.35), foliage=(0.20, 0.35, 0.15), snow=0.0, fog=250.0, noise=0.04, lit=1.0),
    "autumn":   dict(bright=0.92, tint=(1.08, 0.98, 0.88), sun=200.0, ambient=0.65, sky=(0.65, 0.72, 0.85), foliage=(0.75, 0.40, 0.10), snow=0.0, fog=200.0, noise=0.02, lit=0.0),
    "winter":   dict(bright=1.05, tint=(0.92, 0.97, 1.08), sun=170.0, ambient=0.80, sky=(0.78, 0.80, 0.84), foliage=(0.35, 0.30, 0.25), snow=1.0, fog=150.0, noise=0.03, lit=0.0),
    "rain":     dict(bright=0.65, tint=(0.90, 0.95, 1.00), sun=135.0, ambient=0.90, sky=(0.45, 0.47, 0.50), foliage=(0.15, 0.35, 0.15), snow=0.0, fog=60.0, noise=0.045, lit=0.3),
}


@dataclass
class WorldConfig:
    """Every knob of the synthetic world, in one place.

    Geometry is in metres, angles in degrees. The *difficulty knobs* (what notebook 01 sweeps) are
    ``position_jitter``, ``heading_jitter``, ``condition_strength``, ``occluder_rate`` and
    ``num_facade_types`` / ``colour_variation`` (perceptual aliasing).
    """

    preset: str = "city"
    size: str = "tiny"
    image_size: tuple[int, int] = (32, 48)       # (H, W) pixels
    fov: float = 90.0                             # horizontal field of view
    camera_height: float = 1.8
    view_distance: float = 150.0                  # geometry farther than this is not rendered
    # --- city geometry ---
    blocks: tuple[int, int] = (10, 3)             # blocks along x, y
    block_size: float = 40.0
    street_width: float = 14.0
    place_spacing: float = 10.0                   # database places along streets
    headings: int = 4                             # database headings per place (street-relative)
    heading_offset: float = 45.0                  # first heading relative to the street (45 = diagonal views)
    queries_per_place: float = 3.0
    # --- route geometry ---
    num_frames: int = 900
    frame_spacing: float = 5.0
    frames_per_group: int = 5                     # place groups (MSLS unique_cluster analogue)
    # --- appearance / aliasing ---
    num_facade_types: int = 10
    colour_variation: float = 0.12
    # --- query difficulty ---
    db_condition: str = "summer"
    query_conditions: tuple[str, ...] = ("overcast", "dusk", "autumn", "winter", "rain")
    condition_strength: float = 0.5               # 0 = queries look like the database condition, 1 = full
    position_jitter: float = 3.0                  # std of query position noise (m); route: along-track
    heading_jitter: float = 8.0                   # std of query heading noise
    pitch_jitter: float = 1.0                     # std of horizon shift (pixels)
    occluder_rate: float = 0.6                    # mean number of occluders (cars/people) per query
    # --- splits and evaluation ---
    split_fractions: tuple[float, float, float] = (0.5, 0.2, 0.3)
    pos_radius: float = 25.0
    train_pos_radius: float = 10.0

    def __post_init__(self):
        if self.preset not in PRESETS:
            raise ValueError(f"unknown preset {self.preset!r}; choose one of {sorted(PRESETS)}")
        for c in (self.db_condition, *self.query_conditions):
            if c not in CONDITIONS:
                raise ValueError(f"unknown condition {c!r}; choose from {sorted(CONDITIONS)}")
        h, w = self.image_size
        if not (8 <= h <= 256 and 8 <= w <= 256):
            raise ValueError(f"image_size must be between 8 and 256 pixels per side, got {self.image_size}")
        for name in ("position_jitter", "heading_jitter", "pitch_jitter", "occluder_rate",
                     "colour_variation", "condition_strength"):
            if getattr(self, name) < 0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)}")
        if self.condition_strength > 1:
            raise ValueError(f"condition_strength must be in [0, 1], got {self.condition_strength}")
        if self.num_facade_types < 1:
            raise ValueError(f"num_facade_types must be >= 1, got {self.num_facade_types}")
        fr = np.asarray(self.split_fractions, dtype=float)
        if fr.shape != (3,) or (fr <= 0).any() or abs(fr.sum() - 1) > 1e-6:
            raise ValueError(f"split_fractions must be three positive numbers summing to 1, got {self.split_fractions}")


PRESETS = {
    "city": dict(),
    "route": dict(db_condition="summer", query_conditions=("winter",), position_jitter=0.8,
                  heading_jitter=2.0, occluder_rate=0.0, split_fractions=(0.6, 0.2, 0.2)),
}
SIZES = {
    "tiny": dict(),
    "small": dict(blocks=(20, 6), num_frames=3000),
}


@dataclass
class VPRDataset(Split):
    """A geotagged database/query set, with the fields every notebook uses.

    Images are uint8 (N, H, W, 3); UTM positions float64 (N, 2) in metres; headings in degrees;
    conditions are indices into ``condition_names``; splits are indices into ``SPLITS``;
    ``*_place`` are place-group ids (the MSLS ``unique_cluster`` analogue used by CliqueMining).
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
            if f.name.startswith("db_"):
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


# ----------------------------------------------------------------------------------------------
# Scene description: vertical wall segments (facades, trees, houses, poles) + a skyline ring.
# ----------------------------------------------------------------------------------------------
# kind ids
WALL, TREE, POLE, FENCE = 0, 1, 2, 3


@dataclass
class Scene:
    a: np.ndarray        # (S, 2) segment start
    b: np.ndarray        # (S, 2) segment end
    z0: np.ndarray       # (S,) bottom height
    z1: np.ndarray       # (S,) top height
    kind: np.ndarray     # (S,) WALL/TREE/POLE/FENCE
    style: np.ndarray    # (S,) facade style id
    colour: np.ndarray   # (S, 3) base colour
    u0: np.ndarray       # (S,) texture offset along the wall (m)
    sky_center: np.ndarray
    sky_radius: float
    sky_profile: np.ndarray  # (360*4,) skyline elevation (m at sky_radius) per 0.25 degree
    ground_kind: str          # "city" or "route"
    road: dict                # parameters for the ground texture


def _facade_styles(rng: np.random.Generator, n: int) -> np.ndarray:
    """(n, 9) facade style table: base rgb, window spacing, floor height, window w/h fraction,
    band flag, shop-floor flag."""
    palette = np.array([[0.72, 0.38, 0.28], [0.80, 0.75, 0.62], [0.55, 0.55, 0.58], [0.85, 0.82, 0.78],
                        [0.45, 0.30, 0.22], [0.62, 0.70, 0.75], [0.78, 0.62, 0.40], [0.35, 0.38, 0.45],
                        [0.70, 0.55, 0.55], [0.58, 0.65, 0.50], [0.90, 0.88, 0.70], [0.40, 0.45, 0.40]])
    st = np.empty((n, 9))
    st[:, :3] = palette[np.arange(n) % len(palette)] + rng.normal(0, 0.04, (n, 3))
    st[:, 3] = rng.uniform(1.6, 4.0, n)      # window spacing
    st[:, 4] = rng.uniform(2.6, 4.2, n)      # floor height
    st[:, 5] = rng.uniform(0.3, 0.75, n)     # window width fraction
    st[:, 6] = rng.uniform(0.3, 0.7, n)      # window height fraction
    st[:, 7] = rng.random(n) < 0.4           # horizontal bands
    st[:, 8] = rng.random(n) < 0.5           # shop floor
    return np.clip(st, 0, None)


def _skyline(rng: np.random.Generator, kind: str) -> np.ndarray:
    """Skyline elevation (metres at the ring radius) sampled every 0.25 degrees around the world."""
    n = 1440
    ang = np.arange(n) * 2 * np.pi / n
    prof = np.zeros(n)
    for f in range(1, 24):
        amp = rng.normal(0, 1.0 / f)
        prof += amp * np.cos(f * ang + rng.uniform(0, 2 * np.pi))
    prof = (prof - prof.min()) / (np.ptp(prof) + 1e-9)
    if kind == "city":
        # blocky towers: quantise into steps of random width
        steps = np.repeat(rng.uniform(0, 1, 180), 8)
        prof = 0.5 * prof + 0.5 * steps * (rng.random(1440) > 0.0)
        return 20 + 140 * prof
    return 10 + 120 * prof


def _add_segments(store: dict, a, b, z0, z1, kind, style, colour, u0):
    for k, v in zip(("a", "b", "z0", "z1", "kind", "style", "colour", "u0"), (a, b, z0, z1, kind, style, colour, u0)):
        store.setdefault(k, []).append(np.asarray(v, dtype=np.float64))


def _tree_segments(store, pos: np.ndarray, rng: np.random.Generator, colour_scale: float = 1.0):
    """A tree = two crossed vertical quads (visible from any side)."""
    n = len(pos)
    r = rng.uniform(1.5, 3.0, n)
    h = rng.uniform(5.0, 10.0, n)
    col = np.clip(np.array([0.2, 0.5, 0.15]) + rng.normal(0, 0.05 * colour_scale, (n, 3)), 0, 1)
    for ang in (0.25 * np.pi, 0.75 * np.pi):
        d = np.stack([np.cos(ang + rng.uniform(-0.2, 0.2, n)), np.sin(ang + rng.uniform(-0.2, 0.2, n))], 1) * r[:, None]
        _add_segments(store, pos - d, pos + d, np.zeros(n), h, np.full(n, TREE), rng.integers(0, 4, n), col, np.zeros(n))


def _build_city(cfg: WorldConfig, rng: np.random.Generator):
    styles = _facade_styles(rng, cfg.num_facade_types)
    bx, by = cfg.blocks
    pitch = cfg.block_size + cfg.street_width
    half = cfg.street_width / 2
    store: dict = {}
    # Buildings along every block side: each block side split into buildings of random width.
    for i in range(-1, bx + 1):          # one extra ring of blocks around the streets
        for j in range(-1, by + 1):
            x0, y0 = i * pitch + half, j * pitch + half
            x1, y1 = x0 + cfg.block_size, y0 + cfg.block_size
            corners = [(x0, y0), (x1, y0), (x1, y1), (x0, y1)]
            for c in range(4):
                p, q = np.array(corners[c]), np.array(corners[(c + 1) % 4])
                length = np.linalg.norm(q - p)
                cuts = [0.0]
                while cuts[-1] < length - 4:
                    cuts.append(min(length, cuts[-1] + rng.uniform(6, 15)))
                cuts[-1] = length
                cuts = np.array(cuts)
                nb = len(cuts) - 1
                t0, t1 = cuts[:-1] / length, cuts[1:] / length
                a = p + (q - p) * t0[:, None]
                b = p + (q - p) * t1[:, None]
                st = rng.integers(0, cfg.num_facade_types, nb)
                col = np.clip(styles[st, :3] + rng.normal(0, cfg.colour_variation, (nb, 3)), 0.05, 1)
                h = rng.uniform(6, 26, nb)
                _add_segments(store, a, b, np.zeros(nb), h, np.full(nb, WALL), st, col, rng.uniform(0, 50, nb))
    # Street trees on some sidewalks.
    xs, ys = np.arange(bx + 1) * pitch, np.arange(by + 1) * pitch
    L_x, L_y = bx * pitch, by * pitch
    tree_pos = []
    for y in ys:
        t = np.arange(5, L_x, 11.0) + rng.uniform(-2, 2)
        keep = rng.random(len(t)) < 0.3
        side = np.where(rng.random(len(t)) < 0.5, -1, 1) * (half - 1.0)
        tree_pos.append(np.stack([t[keep], y + side[keep]], 1))
    for x in xs:
        t = np.arange(5, L_y, 11.0) + rng.uniform(-2, 2)
        keep = rng.random(len(t)) < 0.3
        side = np.where(rng.random(len(t)) < 0.5, -1, 1) * (half - 1.0)
        tree_pos.append(np.stack([x + side[keep], t[keep]], 1))
    tree_pos = np.concatenate(tree_pos)
    # no trees in intersections
    near = (np.abs(((tree_pos[:, 0] + pitch / 2) % pitch) - pitch / 2) < half) & \
           (np.abs(((tree_pos[:, 1] + pitch / 2) % pitch) - pitch / 2) < half)
    _tree_segments(store, tree_pos[~near], rng)
    scene = _finish_scene(store, rng, "city", center=np.array([L_x / 2, L_y / 2]),
                          road=dict(pitch=pitch, half=half), styles=styles)
    return scene, styles


def _finish_scene(store, rng, kind, center, road, styles) -> Scene:
    arr = {k: (np.concatenate(v) if v[0].ndim else np.asarray(v)) for k, v in store.items()}
    return Scene(a=arr["a"], b=arr["b"], z0=arr["z0"], z1=arr["z1"], kind=arr["kind"].astype(np.int64),
                 style=arr["style"].astype(np.int64), colour=arr["colour"], u0=arr["u0"],
                 sky_center=center, sky_radius=1000.0, sky_profile=_skyline(rng, kind),
                 ground_kind=kind, road=dict(road, styles=styles))


def _route_track(cfg: WorldConfig, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """A smooth curvy track: positions every frame_spacing m and the forward heading (rad)."""
    n = cfg.num_frames
    curv = np.convolve(rng.normal(0, 1, n + 200), np.ones(60) / 60, mode="same")[100:100 + n]
    heading = np.cumsum(curv * 0.04 * cfg.frame_spacing / 5.0)
    step = cfg.frame_spacing * np.stack([np.cos(heading), np.sin(heading)], 1)
    pos = np.concatenate([[np.zeros(2)], np.cumsum(step, 0)[:-1]])
    return pos, heading


def _build_route(cfg: WorldConfig, rng: np.random.Generator, track: np.ndarray, heading: np.ndarray):
    styles = _facade_styles(rng, cfg.num_facade_types)
    store: dict = {}
    n = len(track)
    normal = np.stack([-np.sin(heading), np.cos(heading)], 1)
    fwd = np.stack([np.cos(heading), np.sin(heading)], 1)
    # landscape "zones" change slowly along the track: forest, open field, village
    zone = np.repeat(rng.integers(0, 3, n // 40 + 2), 40)[:n]
    trees = []
    for side in (-1, 1):
        for k in range(n):
            dens = (0.9, 0.15, 0.3)[zone[k]]
            m = rng.poisson(dens * 1.2)
            if m:
                off = side * rng.uniform(5, 35, m)
                along = rng.uniform(0, cfg.frame_spacing, m)
                trees.append(track[k] + fwd[k] * along[:, None] + normal[k] * off[:, None])
    _tree_segments(store, np.concatenate(trees), rng)
    # houses in villages (and a few elsewhere): boxes of 4 walls
    for k in range(0, n, 3):
        if rng.random() < (0.05, 0.08, 0.45)[zone[k]]:
            side = rng.choice([-1, 1])
            c = track[k] + normal[k] * side * rng.uniform(12, 40)
            w, d = rng.uniform(6, 12), rng.uniform(5, 9)
            ang = heading[k] + rng.uniform(-0.4, 0.4)
            R = np.array([[np.cos(ang), -np.sin(ang)], [np.sin(ang), np.cos(ang)]])
            corners = (np.array([[-w, -d], [w, -d], [w, d], [-w, d]]) / 2) @ R.T + c
            st = rng.integers(0, cfg.num_facade_types)
            col = np.clip(styles[st, :3] + rng.normal(0, cfg.colour_variation, 3), 0.05, 1)
            h = rng.uniform(4, 8)
            for e in range(4):
                _add_segments(store, corners[e][None], corners[(e + 1) % 4][None], [0.0], [h], [WALL], [st],
                              col[None], [rng.uniform(0, 20)])
    # catenary poles every 60 m on one side, fences in fields
    for k in range(0, n, max(1, int(60 / cfg.frame_spacing))):
        p = track[k] + normal[k] * 3.2
        _add_segments(store, (p - fwd[k] * 0.15)[None], (p + fwd[k] * 0.15)[None], [0.0], [7.0], [POLE], [0], [[0.3, 0.3, 0.3]], [0.0])
        p = p + normal[k] * 0.01
        _add_segments(store, (p - normal[k] * 0.15)[None], (p + normal[k] * 0.15)[None], [0.0], [7.0], [POLE], [0], [[0.3, 0.3, 0.3]], [0.0])
    for k in range(0, n - 4, 4):
        if zone[k] == 1 and rng.random() < 0.5:
            side = rng.choice([-1, 1])
            p, q = track[k] + normal[k] * side * 6, track[k + 4] + normal[k + 4] * side * 6
            _add_segments(store, p[None], q[None], [0.0], [1.2], [FENCE], [0], [[0.55, 0.4, 0.25]], [0.0])
    center = track.mean(0)
    # the rails: a KD-tree over the track sampled every 0.25 m (distance to the polyline)
    fine = np.concatenate([track[:-1] + (track[1:] - track[:-1]) * f for f in np.linspace(0, 1, 20, endpoint=False)])
    return _finish_scene(store, rng, "route", center=center, road=dict(track_tree=cKDTree(fine)), styles=styles)


# ----------------------------------------------------------------------------------------------
# Rendering
# ----------------------------------------------------------------------------------------------
def _cond_params(cfg: WorldConfig, name: str) -> dict:
    """Condition parameters, interpolated from the database condition by ``condition_strength``."""
    base, tgt = CONDITIONS[cfg.db_condition], CONDITIONS[name]
    s = cfg.condition_strength if name != cfg.db_condition else 0.0
    out = {}
    for k in base:
        b, t = np.asarray(base[k], dtype=float), np.asarray(tgt[k], dtype=float)
        if k == "sun":  # interpolate angles the short way
            d = (t - b + 180) % 360 - 180
            out[k] = float(b + s * d)
        elif k == "fog":  # interpolate in 1/distance
            out[k] = float(1.0 / ((1 - s) / b + s / t))
        else:
            out[k] = b + s * (t - b)
    return out


def _hash01(*ints) -> np.ndarray:
    """Deterministic per-element pseudo random numbers in [0, 1) from integer arrays."""
    h = np.uint64(1469598103934665603)
    out = np.full(np.broadcast(*ints).shape, h, dtype=np.uint64)
    for x in ints:
        out ^= np.asarray(x).astype(np.int64).astype(np.uint64)
        out *= np.uint64(1099511628211)
        out ^= out >> np.uint64(29)
    return (out % np.uint64(1 << 24)).astype(np.float64) / float(1 << 24)


def _visible_segments(scene: Scene, cfg: WorldConfig, pos: np.ndarray, heading_deg: np.ndarray) -> np.ndarray:
    """Indices of the segments each camera may see, padded with -1 to a rectangular (N, S) table."""
    pts = np.stack([scene.a, (scene.a + scene.b) / 2, scene.b], 1)               # (S_all, 3, 2)
    tree = cKDTree(pts[:, 1])
    half_len = np.linalg.norm(scene.b - scene.a, axis=1).max() / 2
    near = tree.query_ball_point(pos, r=cfg.view_distance + half_len)
    half_fov = np.radians(cfg.fov / 2 + 12)
    rows = []
    for i, idx in enumerate(near):
        idx = np.asarray(idx, dtype=np.int64)
        rel = pts[idx] - pos[i]                                                  # (s, 3, 2)
        dist = np.linalg.norm(rel, axis=-1)
        ang = np.arctan2(rel[..., 1], rel[..., 0]) - np.radians(heading_deg[i])
        ang = (ang + np.pi) % (2 * np.pi) - np.pi
        keep = ((np.abs(ang) < half_fov) & (dist < cfg.view_distance)).any(1) | (dist.min(1) < 12)
        rows.append(idx[keep])
    width = max(1, max(len(r) for r in rows))
    out = np.full((len(rows), width), -1, dtype=np.int64)
    for i, r in enumerate(rows):
        out[i, :len(r)] = r
    return out


# Rendering constants: lengths in metres, colours rgb in [0, 1]. Any change of a value changes pixels
# (tests/test_synthetic.py pins rendered worlds by hash).
NEAR_CLIP = 0.3                    # wall hits nearer than this to the camera are ignored
GROUND_RANGE = 10                  # the ground plane is drawn up to GROUND_RANGE x view_distance
# Trees are two crossed quads (_tree_segments) textured in quad coordinates: `across` runs -0.5..0.5
# over the quad's width, `up` is the height over the tree's height. Canopy = an ellipse, trunk = a strip.
TREE_CROWN_CENTRE = 0.62           # canopy centre height and trunk top (fraction of the tree height)
TREE_CROWN_AXES2 = (0.25, 0.16)    # squared semi-axes of the canopy ellipse (across, up)
TREE_TRUNK_HALF_WIDTH = 0.07       # half width of the trunk (fraction of the quad width)
LEAF_CELLS_PER_M = 3               # leaf gaps: one hash value per 1/3 m x 1/3 m cell of the quad
SNOW_LEAF_LOSS = 0.75              # fraction of the leaves gone at snow = 1
# Fences: a post every FENCE_POST_SPACING m, FENCE_POST_WIDTH wide, and one rail.
FENCE_POST_SPACING, FENCE_POST_WIDTH = 2.0, 0.25
FENCE_RAIL_HEIGHT, FENCE_RAIL_HALF_HEIGHT = 0.9, 0.12
# Facades (window spacing, floor height and window size are per style, in the scene's style table).
FACADE_BAND_FROM = 0.88            # styles with bands: the top 12 % of every floor is a dark band
SHOP_TOP = 0.8                     # shop windows (styles with a shop floor): up to 0.8 floor heights,
SHOP_BOTTOM = 0.4                  # from 0.4 m above the street,
SHOP_BAY, SHOP_WINDOW = 6.0, 4.5   # 4.5 m of glass in every 6 m bay
ROOF_TRIM = 0.6                    # a dark trim this high (m) under the roofline
TRIM_DARKEN = 0.6                  # bands and roof trim: base colour x 0.6
LIT_WINDOW_SHARE = 0.5             # hash threshold: half of the windows can be lit ...
LIT_THRESHOLD = 0.5                # ... and are, when the condition's `lit` exceeds this
# Ground.
SIDEWALK_WIDTH = 3.0               # city: sidewalk along the blocks, inside the street's half width
LANE_MARKING_HALF_WIDTH = 0.15     # city: dashed centre line of each street between intersections
DASH_PERIOD, DASH_LENGTH = 6, 3    # (dashes along x + y, in metres)
TRACK_HALF_WIDTH = 1.6             # route: ballast bed on each side of the track's centre line
RAIL_BAND = (0.7, 0.9)             # route: the rails, at these distances from the centre line
SNOW_FREE_TRACK = 1.0              # route: no snow this close to the centre line
GRASS_PATCH = 4                    # route: grass brightness varies per 4 m x 4 m patch
# Sky, far skyline and atmosphere.
SKYLINE_DEPTH = 2000.0             # depth (m) of the far skyline, for the fog
FOG_MAX_DEPTH = 5000.0             # depths are clamped to this before the fog falloff
FOG_SKY_FACTOR = 0.8               # the fog's colour is 0.8 x the sky colour


def _rgb(r: float, g: float, b: float) -> np.ndarray:
    """A read-only colour constant."""
    c = np.array([r, g, b])
    c.flags.writeable = False
    return c


TRUNK_COLOUR = _rgb(0.35, 0.25, 0.18)
LIT_WINDOW_COLOUR, DARK_WINDOW_COLOUR = _rgb(1.0, 0.85, 0.45), _rgb(0.12, 0.16, 0.22)
ROAD_COLOUR, SIDEWALK_COLOUR, MARKING_COLOUR = _rgb(0.30, 0.30, 0.32), _rgb(0.62, 0.60, 0.56), _rgb(0.9, 0.9, 0.8)
BALLAST_COLOUR, RAIL_COLOUR, GRASS_COLOUR = _rgb(0.38, 0.34, 0.30), _rgb(0.6, 0.6, 0.62), _rgb(0.25, 0.42, 0.18)
SNOW_COLOUR = _rgb(0.93, 0.94, 0.97)
CITY_SKYLINE_COLOUR, ROUTE_SKYLINE_COLOUR = _rgb(0.42, 0.45, 0.52), _rgb(0.30, 0.40, 0.42)
SNOWY_SKYLINE_COLOUR = _rgb(0.9, 0.9, 0.95)


@dataclass
class _Rays:
    """One ray per pixel of N pinhole cameras of H x W pixels. The world is 2.5-D, so a ray is a column's
    direction on the ground plane and a row's elevation."""

    pos: np.ndarray      # (N, 2) camera positions
    d: np.ndarray        # (N, W, 2) unit ground-plane direction of each column
    corr: np.ndarray     # (W,) cos of the column's angle off the view axis: planar depth = distance x corr
    tan_el: np.ndarray   # (N, H) tangent of each row's elevation angle (pitch jitter included)


@dataclass
class _Hits:
    """The K nearest segment hits of every column ray, nearest first (t = inf where a layer has no hit)."""

    seg: np.ndarray      # (N, W, K) segment index into the scene
    t: np.ndarray        # (N, W, K) distance along the ground-plane ray (m)
    s: np.ndarray        # (N, W, K) where the ray crosses the segment: 0 at its start a, 1 at its end b


@dataclass
class _Frame:
    """The images being drawn: colour, planar depth (for the fog) and which pixels are drawn already."""

    img: np.ndarray      # (N, H, W, 3)
    depth: np.ndarray    # (N, H, W)
    filled: np.ndarray   # (N, H, W) bool

    def draw(self, n_idx, h_idx, w_idx, colour, depth) -> None:
        self.img[n_idx, h_idx, w_idx] = colour
        self.depth[n_idx, h_idx, w_idx] = depth
        self.filled[n_idx, h_idx, w_idx] = True


def _stack_conditions(conds: list[dict]) -> dict[str, np.ndarray]:
    """The condition parameters of N cameras as arrays with one row per camera (sun azimuth in radians)."""
    out = {k: np.array([c[k] for c in conds]) for k in conds[0]}
    out["sun"] = np.array([np.radians(c["sun"]) for c in conds])
    return out


def _camera_rays(cfg: WorldConfig, pos: np.ndarray, heading_deg: np.ndarray, pitch_px: np.ndarray) -> _Rays:
    """Stage 1a: the rays of pinhole cameras (horizontal ``cfg.fov``, square pixels, x right = clockwise);
    ``pitch_px`` moves the horizon up or down by that many pixels."""
    H, W = cfg.image_size
    f = (W / 2) / np.tan(np.radians(cfg.fov) / 2)                                # focal length (pixels)
    cols = (np.arange(W) - W / 2 + 0.5) / f
    ang = np.radians(heading_deg)[:, None] - np.arctan(cols)[None, :]           # (N, W)
    d = np.stack([np.cos(ang), np.sin(ang)], -1)                                 # (N, W, 2)
    corr = 1.0 / np.sqrt(1 + cols ** 2)
    rows = (H / 2 - np.arange(H) - 0.5)[None, :] + pitch_px[:, None]             # (N, H)
    return _Rays(pos=pos, d=d, corr=corr, tan_el=rows / f)                       # vertical: same focal


def _cast_rays(scene: Scene, cfg: WorldConfig, rays: _Rays, heading_deg: np.ndarray, layers: int) -> _Hits:
    """Stage 1b: intersect every column ray with the vertical segments; keep the ``layers`` nearest hits.

    Per-camera culling (:func:`_visible_segments`) keeps the segments near the camera and inside the
    (widened) view frustum, gathered into a padded (N, S) table, so the ray/segment tests are N x W x S
    with S small. Several layers are kept because trees and fences have gaps to see through."""
    pos, d = rays.pos, rays.d
    cand = _visible_segments(scene, cfg, pos, heading_deg)                      # (N, S) indices, -1 = pad
    safe = np.maximum(cand, 0)
    A, e = scene.a[safe], (scene.b - scene.a)[safe]                              # (N, S, 2)
    AO = A - pos[:, None, :]
    den = d[:, :, None, 0] * e[:, None, :, 1] - d[:, :, None, 1] * e[:, None, :, 0]   # (N, W, S)
    num_t = AO[:, None, :, 0] * e[:, None, :, 1] - AO[:, None, :, 1] * e[:, None, :, 0]
    num_s = AO[:, None, :, 0] * d[:, :, None, 1] - AO[:, None, :, 1] * d[:, :, None, 0]
    with np.errstate(divide="ignore", invalid="ignore"):
        t = num_t / den
        s = num_s / den
    ok = ((np.abs(den) > 1e-9) & (t > NEAR_CLIP) & (t < cfg.view_distance) & (s >= 0) & (s <= 1)
          & (cand >= 0)[:, None, :])
    t = np.where(ok, t, np.inf)
    K = min(layers, t.shape[-1])
    if t.shape[-1] > K:
        order = np.argpartition(t, K - 1, axis=-1)[..., :K]
    else:
        order = np.broadcast_to(np.arange(t.shape[-1]), t.shape)
    tk = np.take_along_axis(t, order, -1)
    sk = np.take_along_axis(s, order, -1)
    srt = np.argsort(tk, -1)
    order, tk, sk = (np.take_along_axis(x, srt, -1) for x in (order, tk, sk))     # (N, W, K) nearest first
    seg = np.take_along_axis(np.broadcast_to(safe[:, None, :], t.shape), order, -1)
    return _Hits(seg=seg, t=tk, s=sk)


def _tree_coverage(scene: Scene, u: np.ndarray, z: np.ndarray, seglen: np.ndarray, sgb: np.ndarray,
                   snow: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Where a tree quad is solid: (solid, trunk) masks over (N, H, W).

    The trunk strip, and the canopy ellipse with hashed leaf gaps (more gaps with snow: bare winter
    trees). ``u`` and ``z`` are the texture coordinate along the quad and the height (m), ``seglen``
    (N, W) the quad widths, ``sgb`` the segment of each pixel, ``snow`` (N,) the condition's snow."""
    across = (u - scene.u0[sgb]) / np.maximum(seglen[:, None, :], 1e-6) - 0.5
    up = z / scene.z1[sgb]
    canopy = (across ** 2 / TREE_CROWN_AXES2[0] + (up - TREE_CROWN_CENTRE) ** 2 / TREE_CROWN_AXES2[1]) < 1.0
    trunk = (np.abs(across) < TREE_TRUNK_HALF_WIDTH) & (up < TREE_CROWN_CENTRE)
    uu = np.nan_to_num(u * LEAF_CELLS_PER_M, posinf=0, neginf=0)
    zq = np.nan_to_num(z * LEAF_CELLS_PER_M, posinf=0, neginf=0)
    leaf_keep = _hash01(uu.astype(np.int64), zq.astype(np.int64), sgb) < (1.0 - SNOW_LEAF_LOSS * snow[:, None, None])
    return trunk | (canopy & leaf_keep), trunk


def _fence_coverage(u: np.ndarray, z: np.ndarray) -> np.ndarray:
    """Where a fence is solid: its posts and its rail."""
    return ((u % FENCE_POST_SPACING) < FENCE_POST_WIDTH) | (np.abs(z - FENCE_RAIL_HEIGHT) < FENCE_RAIL_HALF_HEIGHT)


def _facade_albedo(scene: Scene, col: np.ndarray, sgp: np.ndarray, up: np.ndarray, zp: np.ndarray,
                   wall: np.ndarray, lit: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Wall material: the facade texture of the ``wall`` pixels, over their base colour ``col``.

    From the segment's style: a window grid above the ground floor (window spacing, floor height,
    window width/height fractions), shop windows on the ground floor, dark bands under each floor's
    top; every wall has a dark roof trim. Windows are dark glass, or warm light where the condition
    lights windows (``lit``, dusk) and the window's hash picks it. Returns (albedo, glow): glow marks
    the lit windows, which keep their colour whatever the lighting."""
    styles = scene.road["styles"]
    stl = styles[scene.style[sgp] % len(styles)]  # non-wall segments reuse small style ids
    spacing, floor, win_w, win_h, has_band, has_shop = (stl[:, i] for i in range(3, 9))
    win = ((up % spacing) / spacing < win_w) & (((zp % floor) / floor) < win_h) & (zp > floor)
    band = (has_band > 0) & (((zp % floor) / floor) > FACADE_BAND_FROM)
    shop = (has_shop > 0) & (zp < floor * SHOP_TOP) & (zp > SHOP_BOTTOM) & ((up % SHOP_BAY) < SHOP_WINDOW)
    roofline = zp > scene.z1[sgp] - ROOF_TRIM
    lit_on = _hash01((up / spacing).astype(int), (zp / floor).astype(int), sgp) < LIT_WINDOW_SHARE
    glowing = (lit * lit_on) > LIT_THRESHOLD
    glass = wall & (win | shop)
    col = np.where(glass[:, None], np.where(glowing[:, None], LIT_WINDOW_COLOUR, DARK_WINDOW_COLOUR), col)
    col = np.where((wall & (band | roofline))[:, None], col * TRIM_DARKEN, col)
    return col, glass & glowing


def _tree_albedo(col: np.ndarray, tree: np.ndarray, trunk: np.ndarray, foliage: np.ndarray,
                 base: np.ndarray) -> np.ndarray:
    """Tree material: trunk pixels brown, the ``tree`` pixels' canopy in the condition's ``foliage``
    colour, varied per tree by its base colour (x (0.7 + 1.2 base) / 1.3: a channel of 0.5, the mean
    green of :func:`_tree_segments`, keeps the foliage colour)."""
    col = np.where((tree & ~trunk)[:, None], foliage * (0.7 + 0.6 * base / 0.5) / 1.3, col)
    return np.where(trunk[:, None], TRUNK_COLOUR, col)


def _sun_shading(scene: Scene, sgp: np.ndarray, sun: np.ndarray, ambient: np.ndarray) -> np.ndarray:
    """Lambert shading of vertical walls lit from azimuth ``sun`` (rad): ambient + (1 - ambient) x
    |cos(wall normal, sun)| (both faces of a segment alike)."""
    e_p = scene.b[sgp] - scene.a[sgp]
    nrm = np.stack([e_p[:, 1], -e_p[:, 0]], 1) / np.maximum(np.linalg.norm(e_p, axis=1, keepdims=True), 1e-9)
    sun_v = np.stack([np.cos(sun), np.sin(sun)], 1)
    lam = np.abs((nrm * sun_v).sum(1))
    return ambient + (1 - ambient) * lam


def _shade_segment_pixels(scene: Scene, sgp: np.ndarray, up: np.ndarray, zp: np.ndarray, trunk: np.ndarray,
                          cond: dict, n_idx: np.ndarray) -> np.ndarray:
    """Colour (P, 3) of P segment pixels: the material's albedo (walls: facade texture; trees: foliage
    and trunk; poles and fences: their flat base colour) times the sun shading; lit windows glow on top.
    ``sgp``: segment, ``up``/``zp``: texture coordinate and height, ``trunk``: on a tree's trunk,
    ``n_idx``: camera of each pixel."""
    kind = scene.kind[sgp]
    wall = kind == WALL
    col, glow = _facade_albedo(scene, scene.colour[sgp].copy(), sgp, up, zp, wall, cond["lit"][n_idx])
    col = _tree_albedo(col, kind == TREE, trunk, cond["foliage"][n_idx], scene.colour[sgp])
    col = col * _sun_shading(scene, sgp, cond["sun"][n_idx], cond["ambient"][n_idx])[:, None]
    return np.where(glow[:, None], LIT_WINDOW_COLOUR, col)


def _draw_segments(scene: Scene, cfg: WorldConfig, rays: _Rays, hits: _Hits, cond: dict, frame: _Frame) -> None:
    """Stage 2: walls, trees, poles and fences, one hit layer at a time, nearest first.

    A layer covers a pixel where the row's ray meets the hit segment between its bottom and top
    height, the material is solid there (trees and fences have gaps: :func:`_tree_coverage`,
    :func:`_fence_coverage`) and no nearer layer drew it; covered pixels get their material colour
    (:func:`_shade_segment_pixels`) and their planar depth."""
    N, H, W = frame.filled.shape
    for k in range(hits.t.shape[-1]):
        tk_k = hits.t[..., k]                                                    # (N, W)
        valid = np.isfinite(tk_k)
        if not valid.any():
            continue
        sg = hits.seg[..., k]
        plan = tk_k * rays.corr[None, :]                                         # distance along the view axis
        z = cfg.camera_height + plan[:, None, :] * rays.tan_el[:, :, None]      # (N, H, W) height of the hit
        z0, z1 = scene.z0[sg][:, None, :], scene.z1[sg][:, None, :]
        inside = valid[:, None, :] & (z >= z0) & (z <= z1) & ~frame.filled
        # texture coordinate along the segment (m)
        seglen = np.linalg.norm(scene.b[sg] - scene.a[sg], axis=-1)
        u = (hits.s[..., k] * seglen + scene.u0[sg])[:, None, :] * np.ones((1, H, 1))
        kind = scene.kind[sg][:, None, :] * np.ones((1, H, 1), dtype=np.int64)
        sgb = np.broadcast_to(sg[:, None, :], (N, H, W))
        trunk = None
        if (kind == TREE).any():
            tree_solid, trunk = _tree_coverage(scene, u, z, seglen, sgb, cond["snow"])
            inside &= np.where(kind == TREE, tree_solid, True)
        if (kind == FENCE).any():
            inside &= np.where(kind == FENCE, _fence_coverage(u, z), True)
        if not inside.any():
            continue
        n_idx, h_idx, w_idx = np.nonzero(inside)
        sgp = sg[n_idx, w_idx]
        on_trunk = np.zeros(len(sgp), dtype=bool) if trunk is None else \
            (scene.kind[sgp] == TREE) & trunk[n_idx, h_idx, w_idx]
        col = _shade_segment_pixels(scene, sgp, u[n_idx, h_idx, w_idx], z[n_idx, h_idx, w_idx], on_trunk, cond, n_idx)
        frame.draw(n_idx, h_idx, w_idx, col, plan[n_idx, w_idx])


def _city_ground(gp: np.ndarray, pitch: float, half: float) -> np.ndarray:
    """City ground colour at points ``gp`` (P, 2): streets every ``pitch`` m along x and y (``half``:
    half the street width) with asphalt between the sidewalks and a dashed centre line between the
    intersections; paving on the sidewalks and inside the blocks."""
    ox = np.abs(((gp[:, 0] + pitch / 2) % pitch) - pitch / 2)   # distance to the nearest street's centre line
    oy = np.abs(((gp[:, 1] + pitch / 2) % pitch) - pitch / 2)
    road = (ox < half - SIDEWALK_WIDTH) | (oy < half - SIDEWALK_WIDTH)
    marking = ((ox < LANE_MARKING_HALF_WIDTH) & (oy > half)) | ((oy < LANE_MARKING_HALF_WIDTH) & (ox > half))
    gcol = np.where(road[:, None], ROAD_COLOUR, SIDEWALK_COLOUR)
    return np.where((marking & ((gp.sum(1) % DASH_PERIOD) < DASH_LENGTH))[:, None], MARKING_COLOUR, gcol)


def _route_ground(gp: np.ndarray, track_tree: cKDTree, snow: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Route ground colour at points ``gp`` (P, 2): the track (ballast bed and two rails, from the
    distance to the track's centre line) through patchy grass. Returns (colour, snow cover): no snow
    on the track's middle."""
    dd, _ = track_tree.query(gp)
    track = dd < TRACK_HALF_WIDTH
    patch = _hash01((gp[:, 0] / GRASS_PATCH).astype(int), (gp[:, 1] / GRASS_PATCH).astype(int))
    grass = GRASS_COLOUR * (0.85 + 0.3 * patch)[:, None]
    gcol = np.where(track[:, None], BALLAST_COLOUR, grass)
    gcol = np.where((track & (dd > RAIL_BAND[0]) & (dd < RAIL_BAND[1]))[:, None], RAIL_COLOUR, gcol)
    return gcol, snow * (~track | (dd > SNOW_FREE_TRACK))


def _draw_ground(scene: Scene, cfg: WorldConfig, rays: _Rays, cond: dict, frame: _Frame) -> None:
    """Stage 3: the ground plane below the horizon where no segment was drawn, up to GROUND_RANGE x
    view_distance: the city's or the route's texture, under the condition's snow, lit by
    0.6 + 0.4 x ambient (no sun shading)."""
    below = rays.tan_el < 0                                                       # (N, H)
    with np.errstate(divide="ignore"):
        tg = np.where(below, cfg.camera_height / np.maximum(-rays.tan_el, 1e-9), np.inf)   # planar distance (N, H)
    gmask = below[:, :, None] & ~frame.filled & (tg[:, :, None] < GROUND_RANGE * cfg.view_distance)
    n_idx, h_idx, w_idx = np.nonzero(gmask)
    dist = tg[n_idx, h_idx] / rays.corr[w_idx]
    gp = rays.pos[n_idx] + rays.d[n_idx, w_idx] * dist[:, None]                  # ground point of each pixel
    snow = cond["snow"][n_idx]
    if scene.ground_kind == "city":
        gcol = _city_ground(gp, scene.road["pitch"], scene.road["half"])
    else:
        gcol, snow = _route_ground(gp, scene.road["track_tree"], snow)
    gcol = gcol * (1 - snow[:, None]) + SNOW_COLOUR * snow[:, None]
    amb = cond["ambient"][n_idx]
    frame.draw(n_idx, h_idx, w_idx, gcol * (0.6 + 0.4 * amb)[:, None], tg[n_idx, h_idx])


def _draw_sky(scene: Scene, rays: _Rays, cond: dict, frame: _Frame) -> None:
    """Stage 4: every pixel still empty. The far skyline is a height profile on a ring of radius
    ``sky_radius`` around the world centre (almost no parallax), blended towards the sky colour and
    whitened by snow; above it the sky, a little darker towards the top of the image."""
    H = frame.filled.shape[1]
    n_idx, h_idx, w_idx = np.nonzero(~frame.filled)
    origin = rays.pos[n_idx] - scene.sky_center                                   # camera, from the ring's centre
    dv = rays.d[n_idx, w_idx]
    bq = (origin * dv).sum(1)
    cq = (origin ** 2).sum(1) - scene.sky_radius ** 2
    tr_ = -bq + np.sqrt(np.maximum(bq ** 2 - cq, 0))                              # distance to the ring
    hit = origin + dv * tr_[:, None]
    n_prof = len(scene.sky_profile)
    a_idx = ((np.arctan2(hit[:, 1], hit[:, 0]) % (2 * np.pi)) / (2 * np.pi) * n_prof).astype(int) % n_prof
    elev = scene.sky_profile[a_idx] / tr_
    is_sky = rays.tan_el[n_idx, h_idx] * rays.corr[w_idx] > elev
    skyc = cond["sky"][n_idx]
    snow = cond["snow"][n_idx]
    grad = (0.85 + 0.15 * np.clip(h_idx / H * 2, 0, 1))[:, None]
    far_colour = CITY_SKYLINE_COLOUR if scene.ground_kind == "city" else ROUTE_SKYLINE_COLOUR
    farc = 0.45 * skyc + 0.55 * far_colour * (1 - 0.5 * snow)[:, None] + 0.45 * snow[:, None] * SNOWY_SKYLINE_COLOUR
    frame.draw(n_idx, h_idx, w_idx, np.where(is_sky[:, None], skyc * grad, farc),
               np.where(is_sky, np.inf, SKYLINE_DEPTH))


def _atmosphere(img: np.ndarray, depth: np.ndarray, cond: dict) -> np.ndarray:
    """Stage 5: fog (a mix towards FOG_SKY_FACTOR x the sky colour, 1 - exp(-depth / fog distance)),
    then the condition's global brightness and colour tint; clipped to [0, 1]."""
    fog = cond["fog"][:, None, None]
    skyc = cond["sky"][:, None, None, :]
    fogmix = 1 - np.exp(-np.minimum(depth, FOG_MAX_DEPTH) / fog)
    img = img * (1 - fogmix[..., None]) + FOG_SKY_FACTOR * skyc * fogmix[..., None]
    bright = cond["bright"][:, None, None, None]
    tint = cond["tint"][:, None, None, :]
    return np.clip(img * bright * tint, 0, 1)


def _render(scene: Scene, cfg: WorldConfig, pos: np.ndarray, heading_deg: np.ndarray, pitch_px: np.ndarray,
            conds: list[dict], layers: int = 4) -> np.ndarray:
    """Ray-cast a batch of cameras. Returns float images (N, H, W, 3) in [0, 1] before noise.

    Each stage draws only the pixels the stages before it left empty:

    1. rays (:func:`_camera_rays`) and their ``layers`` nearest segment hits (:func:`_cast_rays`);
    2. walls, trees, poles and fences (:func:`_draw_segments`): coverage, material, sun shading;
    3. the ground plane (:func:`_draw_ground`);
    4. the far skyline and the sky (:func:`_draw_sky`);
    5. fog, brightness and tint over the whole image (:func:`_atmosphere`).
    """
    H, W = cfg.image_size
    N = len(pos)
    rays = _camera_rays(cfg, pos, heading_deg, pitch_px)
    hits = _cast_rays(scene, cfg, rays, heading_deg, layers)
    cond = _stack_conditions(conds)
    frame = _Frame(img=np.zeros((N, H, W, 3)), depth=np.full((N, H, W), np.inf),
                   filled=np.zeros((N, H, W), dtype=bool))
    _draw_segments(scene, cfg, rays, hits, cond, frame)
    _draw_ground(scene, cfg, rays, cond, frame)
    _draw_sky(scene, rays, cond, frame)
    return _atmosphere(frame.img, frame.depth, cond)


def _postprocess(img: np.ndarray, conds: list[dict], occluders: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Sensor noise, rain streaks and occluders (cars, pedestrians), then uint8."""
    N, H, W, _ = img.shape
    img = img.copy()
    for i in range(N):
        for _ in range(int(occluders[i])):
            if rng.random() < 0.65:   # car: wide box in the lower half
                w, h = int(rng.integers(W // 5, W // 2)), int(rng.integers(H // 6, H // 3))
                x, y = int(rng.integers(-w // 3, W - w // 2)), int(rng.integers(H // 2, H - h // 2))
            else:                     # pedestrian: thin tall box
                w, h = int(rng.integers(2, max(3, W // 12))), int(rng.integers(H // 4, H // 2))
                x, y = int(rng.integers(0, W - w)), int(rng.integers(H // 3, H - h // 2))
            colr = rng.uniform(0.05, 0.95, 3) * (0.4 + 0.6 * conds[i]["bright"])
            img[i, max(y, 0):y + h, max(x, 0):x + w] = colr
        noise = conds[i]["noise"]
        img[i] += rng.normal(0, noise, (H, W, 3))
        if noise > 0.04:  # rain streaks
            m = rng.random((H, W)) < 0.02
            img[i][np.roll(m, 1, 0) | m] += 0.15
    return (np.clip(img, 0, 1) * 255 + 0.5).astype(np.uint8)


def _render_all(scene, cfg, pos, heading, pitch, cond_names, occluders, rng, chunk: int = 32) -> np.ndarray:
    params = {c: _cond_params(cfg, c) for c in set(cond_names)}
    out = np.empty((len(pos), *cfg.image_size, 3), dtype=np.uint8)
    # chunk spatially coherent cameras together (fewer candidate segments per chunk)
    order = np.lexsort((pos[:, 1], np.round(pos[:, 0] / 50)))
    for s in range(0, len(pos), chunk):
        idx = order[s:s + chunk]
        conds = [params[cond_names[i]] for i in idx]
        img = _render(scene, cfg, pos[idx], heading[idx], pitch[idx], conds)
        out[idx] = _postprocess(img, conds, occluders[idx], rng)
    return out


# ----------------------------------------------------------------------------------------------
# Camera layouts and splits
# ----------------------------------------------------------------------------------------------
def _split_of(coord: np.ndarray, lo: float, hi: float, fractions, gap: float) -> np.ndarray:
    """Split index (0/1/2) of each coordinate along one axis; -1 inside the gaps between splits."""
    edges = lo + (hi - lo) * np.cumsum([0, *fractions])
    out = np.full(len(coord), -1)
    for k in range(3):
        a = edges[k] + (gap / 2 if k > 0 else -1e9)
        b = edges[k + 1] - (gap / 2 if k < 2 else -1e9)
        out[(coord >= a) & (coord < b)] = k
    return out


def _city_cameras(cfg: WorldConfig, rng: np.random.Generator):
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
    P = len(places)
    hs = cfg.heading_offset + np.arange(cfg.headings) * 360.0 / cfg.headings
    db_pos = np.repeat(places, cfg.headings, 0) + rng.normal(0, 0.3, (P * cfg.headings, 2))
    db_head = (np.repeat(street_dir, cfg.headings) + np.tile(hs, P) + rng.normal(0, 1.0, P * cfg.headings)) % 360
    db_place = np.repeat(np.arange(P), cfg.headings)
    # queries: random places, a random offset along the street, a random database heading + jitter
    nq = int(round(cfg.queries_per_place * P))
    qp = rng.integers(0, P, nq)
    along = rng.uniform(-cfg.place_spacing / 2, cfg.place_spacing / 2, nq)
    sd = np.radians(street_dir[qp])
    q_pos = places[qp] + np.stack([np.cos(sd), np.sin(sd)], 1) * along[:, None]
    q_pos = q_pos + rng.normal(0, cfg.position_jitter, (nq, 2)) * np.array([1.0, 1.0]) * 0.7
    # keep queries on the street (clamp the cross-street offset)
    cross = np.stack([-np.sin(sd), np.cos(sd)], 1)
    off = ((q_pos - places[qp]) * cross).sum(1)
    q_pos -= cross * (off - np.clip(off, -cfg.street_width / 2 + 2, cfg.street_width / 2 - 2))[:, None]
    q_head = (street_dir[qp] + hs[rng.integers(0, cfg.headings, nq)] + rng.normal(0, cfg.heading_jitter, nq)) % 360
    db_split = _split_of(db_pos[:, 0], 0, L_x, cfg.split_fractions, gap=cfg.pos_radius * 1.2)
    q_split = _split_of(q_pos[:, 0], 0, L_x, cfg.split_fractions, gap=cfg.pos_radius * 1.2)
    q_place = cKDTree(places).query(q_pos)[1]
    return db_pos, db_head, db_place, q_pos, q_head, q_place, db_split, q_split


def _route_cameras(cfg: WorldConfig, rng: np.random.Generator, track, heading):
    n = len(track)
    frames = np.arange(n)
    db_pos = track.copy()
    db_head = np.degrees(heading) % 360
    fwd = np.stack([np.cos(heading), np.sin(heading)], 1)
    q_pos = track + fwd * rng.normal(0, cfg.position_jitter, n)[:, None]
    q_head = (db_head + rng.normal(0, cfg.heading_jitter, n)) % 360
    gap_frames = int(np.ceil(cfg.pos_radius * 1.2 / cfg.frame_spacing))
    split = _split_of(frames.astype(float), 0, n, cfg.split_fractions, gap=gap_frames)
    place = frames // cfg.frames_per_group
    return db_pos, db_head, place, q_pos, q_head, place.copy(), split, split.copy()


def make_config(preset: str = "city", size: str = "tiny", **overrides) -> WorldConfig:
    """The :class:`WorldConfig` of a preset and size, with keyword overrides applied."""
    if preset not in PRESETS:
        raise ValueError(f"unknown preset {preset!r}; choose one of {sorted(PRESETS)}")
    if size not in SIZES:
        raise ValueError(f"unknown size {size!r}; choose one of {sorted(SIZES)}")
    valid = {f.name for f in dataclasses.fields(WorldConfig)} - {"preset", "size"}
    bad = sorted(set(overrides) - valid)
    if bad:
        raise ValueError(f"unknown world option(s) {bad}; valid options: {sorted(valid)}")
    kw = {**PRESETS[preset], **SIZES[size], **overrides}
    if preset == "route" and "pos_radius" not in overrides:
        kw["pos_radius"] = 1.01 * kw.get("frame_spacing", WorldConfig.frame_spacing)
        kw.setdefault("train_pos_radius", kw["pos_radius"])
    return WorldConfig(preset=preset, size=size, **kw)


def make_dataset(preset: str = "city", seed: int = 0, size: str = "tiny",
                 splits: Sequence[str] = SPLITS, **overrides) -> VPRDataset:
    """Generate (deterministically from ``seed``) a synthetic VPR dataset.

    ``preset`` is ``"city"`` or ``"route"``; ``size`` is ``"tiny"`` (notebooks, CI) or ``"small"``;
    ``splits`` restricts rendering to some splits (geometry and the other splits' positions are still
    generated, so a split is identical whatever else is rendered); ``overrides`` set any
    :class:`WorldConfig` field (e.g. ``condition_strength=0.5``).
    """
    seed = check_int(seed, "seed", minimum=0)
    cfg = make_config(preset, size, **overrides)
    splits = tuple(splits)
    bad = [s for s in splits if s not in SPLITS]
    if bad or not splits:
        raise ValueError(f"splits must be a non-empty subset of {SPLITS}, got {splits}")
    root = np.random.SeedSequence(seed)
    geo_rng, cam_rng, render_rng, cond_rng = (np.random.default_rng(s) for s in root.spawn(4))
    if preset == "city":
        scene, _ = _build_city(cfg, geo_rng)
        cams = _city_cameras(cfg, cam_rng)
    else:
        track, heading = _route_track(cfg, geo_rng)
        scene = _build_route(cfg, geo_rng, track, heading)
        cams = _route_cameras(cfg, cam_rng, track, heading)
    db_pos, db_head, db_place, q_pos, q_head, q_place, db_split, q_split = cams
    nq = len(q_pos)
    q_cond_idx = cond_rng.integers(0, len(cfg.query_conditions), nq)
    q_pitch = cond_rng.normal(0, cfg.pitch_jitter, nq)
    q_occ = cond_rng.poisson(cfg.occluder_rate, nq)
    names = (cfg.db_condition, *[c for c in cfg.query_conditions if c != cfg.db_condition])
    q_cond_names = [cfg.query_conditions[i] for i in q_cond_idx]
    wanted = [SPLITS.index(s) for s in splits]
    dm, qm = np.isin(db_split, wanted), np.isin(q_split, wanted)
    # per-split render seeds so that a split's pixels do not depend on which other splits are rendered
    split_rngs = [np.random.default_rng(s) for s in np.random.SeedSequence(seed + 7919).spawn(6)]
    db_img = np.zeros((dm.sum(), *cfg.image_size, 3), np.uint8)
    q_img = np.zeros((qm.sum(), *cfg.image_size, 3), np.uint8)
    db_sel, q_sel = np.flatnonzero(dm), np.flatnonzero(qm)
    for k in wanted:
        di = np.flatnonzero(db_split[db_sel] == k)
        qi = np.flatnonzero(q_split[q_sel] == k)
        if len(di):
            g = db_sel[di]
            db_img[di] = _render_all(scene, cfg, db_pos[g], db_head[g], np.zeros(len(g)),
                                     [cfg.db_condition] * len(g), np.zeros(len(g), int), split_rngs[2 * k])
        if len(qi):
            g = q_sel[qi]
            q_img[qi] = _render_all(scene, cfg, q_pos[g], q_head[g], q_pitch[g],
                                    [q_cond_names[i] for i in g], q_occ[g], split_rngs[2 * k + 1])
    q_cond = np.array([names.index(c) for c in q_cond_names], dtype=np.int64)
    # geotags: a route query is tagged with its frame's track position (Nordland's ground truth is
    # frame-aligned), so positives within 1.01 x frame_spacing are exactly frames i-1, i, i+1; the
    # along-track jitter only moves the rendered camera. City queries are tagged where they stand.
    q_tag = db_pos.copy() if preset == "route" else q_pos
    return VPRDataset(
        name=f"{preset}-{size}", config=cfg, seed=seed,
        db_images=db_img, q_images=q_img, db_utm=db_pos[dm], q_utm=q_tag[qm],
        db_heading=db_head[dm], q_heading=q_head[qm],
        db_condition=np.zeros(dm.sum(), np.int64), q_condition=q_cond[qm],
        db_split=db_split[dm], q_split=q_split[qm], db_place=db_place[dm], q_place=q_place[qm],
        condition_names=names, pos_radius=cfg.pos_radius, train_pos_radius=cfg.train_pos_radius,
        extra=dict(rendered_splits=splits, scene=scene),
    )
