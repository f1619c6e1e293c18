"""The renderer: a 2.5-D ray caster over a :class:`~vpr_nb.synthetic.layout.Scene` (numpy only).

:func:`render_all` draws the images of a set of cameras: per chunk of nearby cameras, :func:`_render`
casts one ray per pixel column against the vertical segments and draws, each stage only where the
stages before it left pixels empty, the walls / trees / poles / fences, the ground (the world kind's
texture, ``scene.world.ground``), the far skyline and the sky; then fog, brightness and tint; then
:func:`_postprocess` adds sensor noise, rain streaks and occluders (cars, pedestrians) and quantises
to uint8. Every stage also writes what it drew into a label map (:mod:`~vpr_nb.synthetic.labels`), which
``render_all(..., labels=True)`` returns; per-visit distractors (:mod:`~vpr_nb.synthetic.distractors`) are
segments appended to the scene per chunk, seen only by their own visit's cameras.

The scene knobs it reads are :class:`~vpr_nb.synthetic.config.WorldConfig` fields (``image_size``,
``fov``, ``camera_height``, ``view_distance``, the conditions, ``car_share``); the constants below are
*rendering constants* (materials, colours, occluder boxes, culling margins), not scene knobs.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from scipy.spatial import cKDTree

from .conditions import condition_params, stack_conditions
from .distractors import Distractors, Extension, extend_scene
from .hashing import hash01
from .labels import DISTRACTOR_LABEL, GROUND_LABEL, OBJECT_LABEL, OCCLUDER_LABEL, SKY_LABEL, SKYLINE_LABEL
from .layout import DISTRACTOR, FENCE, TREE, WALL, Scene, rgb

if TYPE_CHECKING:
    from .config import WorldConfig

# Rendering constants: lengths in metres, colours rgb in [0, 1]. Any change of a value changes pixels
# (tests/test_synthetic.py pins rendered worlds by hash). A world kind's ground texture and its
# constants live in the kind's module (vpr_nb.synthetic.kinds).
NEAR_CLIP = 0.3                    # wall hits nearer than this to the camera are ignored
CULL_FOV_MARGIN = 12               # culling keeps segments up to 12 degrees outside the field of view ...
CULL_ALWAYS_NEAR = 12              # ... and every segment with a point nearer than 12 m
LAYERS = 4                         # hits kept per column ray (trees and fences have gaps to see through)
RENDER_CHUNK = 32                  # cameras rendered together ...
CHUNK_STRIP = 50                   # ... sorted by strips of 50 m along x, then by y (fewer candidate segments)
GROUND_RANGE = 10                  # the ground plane is drawn up to GROUND_RANGE x view_distance
# Trees are two crossed quads (layout.tree_segments) textured in quad coordinates: `across` runs -0.5..0.5
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
# Sky, far skyline and atmosphere.
SKYLINE_DEPTH = 2000.0             # depth (m) of the far skyline, for the fog
FOG_MAX_DEPTH = 5000.0             # depths are clamped to this before the fog falloff
FOG_SKY_FACTOR = 0.8               # the fog's colour is 0.8 x the sky colour
# Sensor: conditions with noise above 0.04 (rain) get streaks: 2 % of the pixels and the one below, +0.15.
RAIN_NOISE, RAIN_STREAK_SHARE, RAIN_STREAK_GAIN = 0.04, 0.02, 0.15
# Colours.
TRUNK_COLOUR = rgb(0.35, 0.25, 0.18)
LIT_WINDOW_COLOUR, DARK_WINDOW_COLOUR = rgb(1.0, 0.85, 0.45), rgb(0.12, 0.16, 0.22)
SNOW_COLOUR = rgb(0.93, 0.94, 0.97)
SNOWY_SKYLINE_COLOUR = rgb(0.9, 0.9, 0.95)


def _visible_segments(scene: Scene, cfg: WorldConfig, pos: np.ndarray, heading_deg: np.ndarray) -> np.ndarray:
    """Indices of the segments each camera may see, padded with -1 to a rectangular (N, S) table."""
    pts = np.stack([scene.a, (scene.a + scene.b) / 2, scene.b], 1)               # (S_all, 3, 2)
    tree = cKDTree(pts[:, 1])
    half_len = np.linalg.norm(scene.b - scene.a, axis=1).max() / 2
    near = tree.query_ball_point(pos, r=cfg.view_distance + half_len)
    half_fov = np.radians(cfg.fov / 2 + CULL_FOV_MARGIN)
    rows = []
    for i, idx in enumerate(near):
        idx = np.asarray(idx, dtype=np.int64)
        rel = pts[idx] - pos[i]                                                  # (s, 3, 2)
        dist = np.linalg.norm(rel, axis=-1)
        ang = np.arctan2(rel[..., 1], rel[..., 0]) - np.radians(heading_deg[i])
        ang = (ang + np.pi) % (2 * np.pi) - np.pi
        keep = ((np.abs(ang) < half_fov) & (dist < cfg.view_distance)).any(1) | (dist.min(1) < CULL_ALWAYS_NEAR)
        rows.append(idx[keep])
    width = max(1, max(len(r) for r in rows))
    out = np.full((len(rows), width), -1, dtype=np.int64)
    for i, r in enumerate(rows):
        out[i, :len(r)] = r
    return out


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
    """The images being drawn: colour, planar depth (for the fog), which pixels are drawn already and what
    they show (:data:`~vpr_nb.synthetic.labels.LABEL_NAMES`)."""

    img: np.ndarray      # (N, H, W, 3)
    depth: np.ndarray    # (N, H, W)
    filled: np.ndarray   # (N, H, W) bool
    label: np.ndarray    # (N, H, W) uint8

    def draw(self, n_idx, h_idx, w_idx, colour, depth, label) -> None:
        self.img[n_idx, h_idx, w_idx] = colour
        self.depth[n_idx, h_idx, w_idx] = depth
        self.filled[n_idx, h_idx, w_idx] = True
        self.label[n_idx, h_idx, w_idx] = label


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


def _nearest(t: np.ndarray, k: int) -> np.ndarray:
    """Indices (along the last axis) of the ``k`` smallest entries of ``t``, in no particular order."""
    k = min(k, t.shape[-1])
    if t.shape[-1] > k:
        return np.argpartition(t, k - 1, axis=-1)[..., :k]
    return np.broadcast_to(np.arange(t.shape[-1]), t.shape)


def _cast_rays(scene: Scene, cfg: WorldConfig, rays: _Rays, heading_deg: np.ndarray, layers: int,
               extra: Extension | None = None) -> _Hits:
    """Stage 1b: intersect every column ray with the vertical segments; keep the ``layers`` nearest hits.

    Per-camera culling (:func:`_visible_segments`) keeps the segments near the camera and inside the
    (widened) view frustum, gathered into a padded (N, S) table, so the ray/segment tests are N x W x S
    with S small. Several layers are kept because trees and fences have gaps to see through. ``extra``
    appends per-camera segments (distractors): its scene holds ``scene``'s segments first, then them."""
    pos, d = rays.pos, rays.d
    cand = _visible_segments(scene, cfg, pos, heading_deg)                      # (N, S) indices, -1 = pad
    if extra is not None:
        scene, cand = extra.scene, np.concatenate([cand, extra.cand], 1)
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
    if extra is not None and cfg.distractor_layers > 0:    # the scene's nearest hits, then the distractors' own
        s0 = t.shape[-1] - extra.cand.shape[1]
        order = np.concatenate([_nearest(t[..., :s0], layers), s0 + _nearest(t[..., s0:], cfg.distractor_layers)], -1)
    else:
        order = _nearest(t, layers)
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
    leaf_keep = hash01(uu.astype(np.int64), zq.astype(np.int64), sgb) < (1.0 - SNOW_LEAF_LOSS * snow[:, None, None])
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
    styles = scene.styles
    stl = styles[scene.style[sgp] % len(styles)]  # non-wall segments reuse small style ids
    spacing, floor, win_w, win_h, has_band, has_shop = (stl[:, i] for i in range(3, 9))
    win = ((up % spacing) / spacing < win_w) & (((zp % floor) / floor) < win_h) & (zp > floor)
    band = (has_band > 0) & (((zp % floor) / floor) > FACADE_BAND_FROM)
    shop = (has_shop > 0) & (zp < floor * SHOP_TOP) & (zp > SHOP_BOTTOM) & ((up % SHOP_BAY) < SHOP_WINDOW)
    roofline = zp > scene.z1[sgp] - ROOF_TRIM
    lit_on = hash01((up / spacing).astype(int), (zp / floor).astype(int), sgp) < LIT_WINDOW_SHARE
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
        label = np.where(scene.kind[sgp] == DISTRACTOR, DISTRACTOR_LABEL, OBJECT_LABEL)
        frame.draw(n_idx, h_idx, w_idx, col, plan[n_idx, w_idx], label)

def _draw_ground(scene: Scene, cfg: WorldConfig, rays: _Rays, cond: dict, frame: _Frame) -> None:
    """Stage 3: the ground plane below the horizon where no segment was drawn, up to GROUND_RANGE x
    view_distance: the world kind's texture (``scene.world.ground``), under the condition's snow, lit by
    0.6 + 0.4 x ambient (no sun shading)."""
    below = rays.tan_el < 0                                                       # (N, H)
    with np.errstate(divide="ignore"):
        tg = np.where(below, cfg.camera_height / np.maximum(-rays.tan_el, 1e-9), np.inf)   # planar distance (N, H)
    gmask = below[:, :, None] & ~frame.filled & (tg[:, :, None] < GROUND_RANGE * cfg.view_distance)
    n_idx, h_idx, w_idx = np.nonzero(gmask)
    dist = tg[n_idx, h_idx] / rays.corr[w_idx]
    gp = rays.pos[n_idx] + rays.d[n_idx, w_idx] * dist[:, None]                  # ground point of each pixel
    gcol, snow = scene.world.ground(gp, scene.layout, cond["snow"][n_idx])
    gcol = gcol * (1 - snow[:, None]) + SNOW_COLOUR * snow[:, None]
    amb = cond["ambient"][n_idx]
    frame.draw(n_idx, h_idx, w_idx, gcol * (0.6 + 0.4 * amb)[:, None], tg[n_idx, h_idx], GROUND_LABEL)


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
    farc = 0.45 * skyc + 0.55 * scene.world.skyline_colour * (1 - 0.5 * snow)[:, None] + 0.45 * snow[:, None] * SNOWY_SKYLINE_COLOUR
    frame.draw(n_idx, h_idx, w_idx, np.where(is_sky[:, None], skyc * grad, farc),
               np.where(is_sky, np.inf, SKYLINE_DEPTH), np.where(is_sky, SKY_LABEL, SKYLINE_LABEL))


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
            conds: list[dict], layers: int = LAYERS, extra: Extension | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Ray-cast a batch of cameras. Returns float images (N, H, W, 3) in [0, 1] before noise, and their
    label maps (N, H, W); ``extra``: per-camera segments (:func:`~vpr_nb.synthetic.distractors.extend_scene`).

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
    hits = _cast_rays(scene, cfg, rays, heading_deg, layers, extra)
    if extra is not None:
        scene = extra.scene
    cond = stack_conditions(conds)
    frame = _Frame(img=np.zeros((N, H, W, 3)), depth=np.full((N, H, W), np.inf),
                   filled=np.zeros((N, H, W), dtype=bool), label=np.zeros((N, H, W), dtype=np.uint8))
    _draw_segments(scene, cfg, rays, hits, cond, frame)
    _draw_ground(scene, cfg, rays, cond, frame)
    _draw_sky(scene, rays, cond, frame)
    return _atmosphere(frame.img, frame.depth, cond), frame.label


def _postprocess(img: np.ndarray, conds: list[dict], occluders: np.ndarray, car_share: float,
                 rng: np.random.Generator, label: np.ndarray) -> np.ndarray:
    """Occluders (a share ``car_share`` of cars: wide boxes in the lower half; the rest pedestrians:
    thin tall boxes; marked in ``label``, in place), sensor noise and rain streaks, then uint8."""
    N, H, W, _ = img.shape
    img = img.copy()
    for i in range(N):
        for _ in range(int(occluders[i])):
            if rng.random() < car_share:   # car: wide box in the lower half
                w, h = int(rng.integers(W // 5, W // 2)), int(rng.integers(H // 6, H // 3))
                x, y = int(rng.integers(-w // 3, W - w // 2)), int(rng.integers(H // 2, H - h // 2))
            else:                     # pedestrian: thin tall box
                w, h = int(rng.integers(2, max(3, W // 12))), int(rng.integers(H // 4, H // 2))
                x, y = int(rng.integers(0, W - w)), int(rng.integers(H // 3, H - h // 2))
            colr = rng.uniform(0.05, 0.95, 3) * (0.4 + 0.6 * conds[i]["bright"])
            img[i, max(y, 0):y + h, max(x, 0):x + w] = colr
            label[i, max(y, 0):y + h, max(x, 0):x + w] = OCCLUDER_LABEL
        noise = conds[i]["noise"]
        img[i] += rng.normal(0, noise, (H, W, 3))
        if noise > RAIN_NOISE:  # rain streaks
            m = rng.random((H, W)) < RAIN_STREAK_SHARE
            img[i][np.roll(m, 1, 0) | m] += RAIN_STREAK_GAIN
    return (np.clip(img, 0, 1) * 255 + 0.5).astype(np.uint8)


def render_all(scene: Scene, cfg: WorldConfig, pos: np.ndarray, heading: np.ndarray, pitch: np.ndarray,
               cond_names: list[str], occluders: np.ndarray, rng: np.random.Generator,
               chunk: int = RENDER_CHUNK, *, distractors: Distractors | None = None,
               labels: bool = False) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
    """uint8 images (N, H, W, 3) of N cameras at ``pos`` (N, 2) facing ``heading`` (degrees), horizon
    shifted by ``pitch`` (pixels), in conditions ``cond_names``, with ``occluders`` each; ``rng`` draws
    the occluders and the sensor noise, in the order of the chunks. ``distractors`` (one visit per camera,
    :func:`~vpr_nb.synthetic.distractors.place_distractors`) are drawn with the scene; ``rng`` draws
    nothing for them. With ``labels`` also returns the uint8 label maps (N, H, W)
    (:data:`~vpr_nb.synthetic.labels.LABEL_NAMES`); the images are the same either way."""
    params = {c: condition_params(cfg, c) for c in set(cond_names)}
    out = np.empty((len(pos), *cfg.image_size, 3), dtype=np.uint8)
    out_label = np.empty((len(pos), *cfg.image_size), dtype=np.uint8)
    # chunk spatially coherent cameras together (fewer candidate segments per chunk)
    order = np.lexsort((pos[:, 1], np.round(pos[:, 0] / CHUNK_STRIP)))
    for s in range(0, len(pos), chunk):
        idx = order[s:s + chunk]
        conds = [params[cond_names[i]] for i in idx]
        extra = None if distractors is None else extend_scene(scene, distractors.take(idx), pos[idx])
        img, label = _render(scene, cfg, pos[idx], heading[idx], pitch[idx], conds, extra=extra)
        out[idx] = _postprocess(img, conds, occluders[idx], cfg.car_share, rng, label)
        out_label[idx] = label
    return (out, out_label) if labels else out


