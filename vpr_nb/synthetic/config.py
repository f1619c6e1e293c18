"""The world config: every scene knob of the synthetic world in one typed dataclass, :class:`WorldConfig`.

:func:`make_config` builds one from a world kind (``preset``, :mod:`vpr_nb.synthetic.kinds`), a size
and keyword overrides: the dataclass defaults, then the kind's deviations, then its size's, then the
overrides. Each number has one home: a field's default here, or a kind's deviation in its record.

**Scene knobs** (here) say what is in the world and where the cameras stand: sizes, counts, spacings,
shares and ranges in metres (angles in degrees unless a comment says radians), the conditions and
the splits. **Rendering constants** say how a surface is drawn: texture patterns, material colours,
the skyline's shape, occluder boxes in image space, the ray caster's culling margins and layers.
They stay named module constants (:mod:`~vpr_nb.synthetic.render`, :mod:`~vpr_nb.synthetic.layout`
and the kind modules) and are pinned by the pixel hashes of ``tests/test_synthetic.py``.
"""
from __future__ import annotations

import dataclasses
import hashlib
import json
from dataclasses import dataclass

import numpy as np

from .conditions import CONDITIONS
from .kinds import WORLD_KINDS, world_kind

SPLITS = ("train", "val", "test")

# validation tables: (low, high) ranges in metres or fractions, shares in [0, 1], counts >= 1
_RANGES = ("building_width", "building_height", "tree_distance", "house_distance", "house_width", "house_depth",
           "house_height", "tree_radius", "tree_height", "skyline_height", "window_spacing", "floor_height",
           "window_width", "window_height", "roadside_distance", "roadside_height", "roadside_width")
_SHARES = ("street_tree_share", "skyline_blockiness", "band_share", "shop_share", "car_share")
_COUNTS = ("outer_blocks", "headings", "num_frames", "frames_per_group", "track_smoothing", "zone_frames",
           "house_every", "fence_every", "num_facade_types")
_NON_NEGATIVE = ("position_jitter", "heading_jitter", "pitch_jitter", "occluder_rate", "distractor_rate",
                 "colour_variation",
                 "condition_strength", "db_position_jitter", "db_heading_jitter", "street_tree_shift",
                 "tree_colour_variation", "style_colour_variation", "trees_per_frame", "track_curvature",
                 "house_yaw", "corner_remainder", "street_tree_inset", "kerb_margin", "roadside_spacing")
_POSITIVE = ("distractor_height_scale", "fov", "view_distance", "block_size", "street_width", "place_spacing",
             "frame_spacing", "street_tree_spacing", "pole_spacing", "sky_radius", "split_gap", "pos_radius", "train_pos_radius")


@dataclass
class WorldConfig:
    """Every scene knob of the synthetic world, in one place (the module docstring says what is not).

    Geometry is in metres, angles in degrees (radians only where the comment says so). The defaults
    are the city's; a world kind's record (:mod:`vpr_nb.synthetic.kinds`) lists the fields only it
    reads (``WorldKind.fields``) and its deviations. The *difficulty knobs* (what notebook 01 sweeps)
    are ``position_jitter``, ``heading_jitter``, ``condition_strength``, ``occluder_rate`` and
    ``num_facade_types`` / ``colour_variation`` (perceptual aliasing).
    """

    preset: str = "city"                          # the world kind: "city" or "route"
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
    outer_blocks: int = 1                         # rings of blocks around the streets (facades on both sides)
    building_width: tuple[float, float] = (6.0, 15.0)    # buildings along a block side, widths drawn in this range
    building_height: tuple[float, float] = (6.0, 26.0)
    corner_remainder: float = 4.0                 # a block side's last building absorbs a rest shorter than this
    street_tree_start: float = 5.0                # street tree slots: from here along every street ...
    street_tree_spacing: float = 11.0             # ... every 11 m ...
    street_tree_shift: float = 2.0                # ... the whole row shifted by up to +-2 m per street;
    street_tree_share: float = 0.3                # share of the slots with a tree
    street_tree_inset: float = 1.0                # trees stand this far inside the kerb, on a random side
    db_position_jitter: float = 0.3               # std of database camera position noise, per axis
    db_heading_jitter: float = 1.0                # std of database heading noise
    kerb_margin: float = 2.0                      # queries keep this far from the kerb
    # --- route geometry ---
    num_frames: int = 900
    frame_spacing: float = 5.0
    camera_spacing: float = 0.0                   # route density: a frame every this many m along the same track,
                                                  # jitters x camera_spacing / frame_spacing (0 = every frame_spacing m)
    frames_per_group: int = 5                     # place groups (MSLS unique_cluster analogue)
    track_curvature: float = 0.04                 # heading change per 5 m of track per unit of smoothed noise (radians)
    track_smoothing: int = 60                     # frames of the moving average over the curvature noise
    zone_frames: int = 40                         # landscape zones (forest, field, village) change every 40 frames
    zone_tree_density: tuple[float, ...] = (0.9, 0.15, 0.3)     # per zone, x trees_per_frame
    zone_house_share: tuple[float, ...] = (0.05, 0.08, 0.45)    # chance of a house at every house_every-th frame
    zone_fence_share: tuple[float, ...] = (0.0, 0.5, 0.0)       # chance of a fence at every fence_every-th frame
    trees_per_frame: float = 1.2                  # mean trees per frame and side of the track at density 1
    tree_distance: tuple[float, float] = (5.0, 35.0)     # of a tree from the track
    house_every: int = 3                          # frames between house sites
    house_distance: tuple[float, float] = (12.0, 40.0)   # of a house's centre from the track
    house_width: tuple[float, float] = (6.0, 12.0)
    house_depth: tuple[float, float] = (5.0, 9.0)
    house_height: tuple[float, float] = (4.0, 8.0)
    house_yaw: float = 0.4                        # a house turns up to +-0.4 (radians) off the track's direction
    pole_spacing: float = 60.0                    # catenary poles along one side of the track
    pole_offset: float = 3.2                      # their distance from the track
    pole_height: float = 7.0
    fence_every: int = 4                          # a fence spans this many frames
    fence_offset: float = 6.0                     # its distance from the track
    fence_height: float = 1.2
    # --- route content per metre (off by default; notebook 07's route turns them on) ---
    camera_yaw: float = 0.0                       # cameras look this far left of the track's direction (0 = forward)
    roadside_spacing: float = 0.0                 # one roadside object per this many metres per side (0 = none)
    roadside_distance: tuple[float, float] = (2.0, 6.0)  # of a roadside object from the track
    roadside_height: tuple[float, float] = (0.6, 3.5)    # its top (signs hang from 0.6 x their top)
    roadside_width: tuple[float, float] = (0.3, 2.0)
    # --- trees (both kinds) ---
    tree_radius: tuple[float, float] = (1.5, 3.0)        # half width of a tree's two crossed quads
    tree_height: tuple[float, float] = (5.0, 10.0)
    tree_colour_variation: float = 0.05           # per-tree colour noise
    # --- far skyline ---
    sky_radius: float = 1000.0                    # the skyline ring's radius around the world centre
    skyline_height: tuple[float, float] = (20.0, 160.0)  # its lowest and highest point (m, at sky_radius)
    skyline_blockiness: float = 0.5               # share of the profile that is flat-topped towers
    # --- appearance / aliasing ---
    num_facade_types: int = 10
    colour_variation: float = 0.12                # per-building colour noise around its style's colour
    style_colour_variation: float = 0.04          # each style's colour noise around its palette colour
    window_spacing: tuple[float, float] = (1.6, 4.0)     # facade styles draw these in the given ranges
    floor_height: tuple[float, float] = (2.6, 4.2)
    window_width: tuple[float, float] = (0.3, 0.75)      # fraction of the window spacing
    window_height: tuple[float, float] = (0.3, 0.7)      # fraction of the floor height
    band_share: float = 0.4                       # share of the styles with dark bands under each floor
    shop_share: float = 0.5                       # share of the styles with a shop floor
    # --- query difficulty ---
    db_condition: str = "summer"
    query_conditions: tuple[str, ...] = ("overcast", "dusk", "autumn", "winter", "rain")
    condition_strength: float = 0.5               # 0 = queries look like the database condition, 1 = full
    position_jitter: float = 3.0                  # std of query position noise (m); route: along-track
    heading_jitter: float = 8.0                   # std of query heading noise
    pitch_jitter: float = 1.0                     # std of horizon shift (pixels)
    occluder_rate: float = 0.6                    # mean number of occluders (cars/people) per query
    car_share: float = 0.65                       # share of the occluders that are cars (the rest pedestrians)
    distractor_rate: float = 0.0                  # parked cars / pedestrians in 3-D, new at every visit (db and
                                                  # queries): mean number per 10 m of street or track (0 = none)
    distractor_height_scale: float = 1.0          # distractors' heights x this (1: cars 1.3-1.7 m, people 1.5-1.9 m)
    distractor_layers: int = 0                    # > 0: distractor faces get this many ray hits per column of
                                                  # their own, so many distractors never use up the scene's
                                                  # layers (0: they share them, as before)
    # --- splits and evaluation ---
    split_fractions: tuple[float, float, float] = (0.5, 0.2, 0.3)
    split_gap: float = 1.2                        # gap between splits, in units of pos_radius
    pos_radius: float = 25.0
    train_pos_radius: float = 10.0

    def __post_init__(self):
        if self.preset not in WORLD_KINDS:
            raise ValueError(f"unknown preset {self.preset!r}; choose one of {sorted(WORLD_KINDS)}")
        for c in (self.db_condition, *self.query_conditions):
            if c not in CONDITIONS:
                raise ValueError(f"unknown condition {c!r}; choose from {sorted(CONDITIONS)}")
        h, w = self.image_size
        if not (8 <= h <= 256 and 8 <= w <= 256):
            raise ValueError(f"image_size must be between 8 and 256 pixels per side, got {self.image_size}")
        for name in _NON_NEGATIVE:
            if getattr(self, name) < 0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)}")
        for name in _POSITIVE:
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")
        if not -180 <= self.camera_yaw <= 180:
            raise ValueError(f"camera_yaw must be in [-180, 180] degrees, got {self.camera_yaw}")
        cs = self.camera_spacing
        if isinstance(cs, bool) or not isinstance(cs, (int, float)) or not 0 <= cs < np.inf:
            raise ValueError(f"camera_spacing must be a finite distance > 0 in metres (or 0: a frame every "
                             f"frame_spacing m), got {cs!r}")
        if self.condition_strength > 1:
            raise ValueError(f"condition_strength must be in [0, 1], got {self.condition_strength}")
        if isinstance(self.distractor_layers, bool) or not isinstance(self.distractor_layers, (int, np.integer)) \
                or self.distractor_layers < 0:
            raise ValueError(f"distractor_layers must be a whole number >= 0 (0: distractors share the scene's ray "
                             f"hits), got {self.distractor_layers!r}")
        for name in _COUNTS:
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        for name in _SHARES:
            if not 0 <= getattr(self, name) <= 1:
                raise ValueError(f"{name} must be in [0, 1], got {getattr(self, name)}")
        for name in _RANGES:
            lo_hi = getattr(self, name)
            if len(lo_hi) != 2 or not 0 <= lo_hi[0] <= lo_hi[1]:
                raise ValueError(f"{name} must be a range (low, high) with 0 <= low <= high, got {lo_hi}")
        zones = {n: getattr(self, n) for n in ("zone_tree_density", "zone_house_share", "zone_fence_share")}
        if len({len(z) for z in zones.values()}) != 1 or not len(self.zone_tree_density):
            raise ValueError(f"the zone tables must have one entry per zone each, got {zones}")
        if min(min(z) for z in zones.values()) < 0 or max((*self.zone_house_share, *self.zone_fence_share)) > 1:
            raise ValueError(f"zone densities must be >= 0 and zone shares in [0, 1], got {zones}")
        fr = np.asarray(self.split_fractions, dtype=float)
        if fr.shape != (3,) or (fr <= 0).any() or abs(fr.sum() - 1) > 1e-6:
            raise ValueError(f"split_fractions must be three positive numbers summing to 1, got {self.split_fractions}")
        kind = WORLD_KINDS[self.preset]
        if kind.check is not None:
            kind.check(self)

    def scene_fields(self) -> dict:
        """Every field as a dict, less the optional content knobs (:data:`OPTIONAL_CONTENT`) left at their
        defaults: what :meth:`fingerprint` hashes and :mod:`vpr_nb.results` records."""
        return {k: v for k, v in dataclasses.asdict(self).items() if not (k in OPTIONAL_CONTENT and v == _DEFAULTS[k])}

    def fingerprint(self) -> str:
        """sha256 of every field and of the :data:`CONDITIONS` rows this world uses: two configs with the
        same fingerprint describe the same scene (:mod:`vpr_nb.results` keys committed results on it).
        The optional content knobs (:data:`OPTIONAL_CONTENT`) enter it only when set away from their
        defaults: with them off the scene is the one drawn without them, so its fingerprint stays."""
        used = (self.db_condition, *self.query_conditions)
        doc = {"config": self.scene_fields(), "conditions": {c: CONDITIONS[c] for c in sorted(set(used))}}
        return hashlib.sha256(json.dumps(doc, sort_keys=True).encode()).hexdigest()


# Content knobs that are off by default and leave a world's fingerprint alone while they are off.
OPTIONAL_CONTENT = ("camera_yaw", "roadside_spacing", "roadside_distance", "roadside_height", "roadside_width",
                    "camera_spacing", "distractor_rate", "distractor_height_scale", "distractor_layers")
_DEFAULTS = {f.name: f.default for f in dataclasses.fields(WorldConfig)}


def make_config(preset: str = "city", size: str = "tiny", **overrides) -> WorldConfig:
    """The :class:`WorldConfig` of a world kind and size, with keyword overrides applied."""
    kind = world_kind(preset)
    if size not in kind.sizes:
        raise ValueError(f"unknown size {size!r}; choose one of {sorted(kind.sizes)}")
    valid = {f.name for f in dataclasses.fields(WorldConfig)} - {"preset", "size"}
    bad = sorted(set(overrides) - valid)
    if bad:
        raise ValueError(f"unknown world option(s) {bad}; valid options: {sorted(valid)}")
    kw = {**kind.preset, **kind.sizes[size], **overrides}
    if kind.pos_radius_frames is not None and "pos_radius" not in overrides:
        dense = kw.get("camera_spacing")   # the route's density knob: frames every camera_spacing m (kinds/route.py)
        spacing = dense if isinstance(dense, (int, float)) and dense > 0 else kw.get("frame_spacing",
                                                                                     WorldConfig.frame_spacing)
        kw["pos_radius"] = kind.pos_radius_frames * spacing
        kw.setdefault("train_pos_radius", kw["pos_radius"])
    return WorldConfig(preset=preset, size=size, **kw)
