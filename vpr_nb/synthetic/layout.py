"""Scene layout: the world as vertical wall segments (facades, trees, houses, poles, fences) + a skyline ring.

The building blocks every world kind lays out its scene with (:mod:`vpr_nb.synthetic.kinds`): a
:class:`SegmentStore` to add segments to, the facade style library (:func:`facade_styles`), trees as
two crossed quads (:func:`tree_segments`), the far skyline (:func:`skyline`), and :func:`finish_scene`,
which freezes them into a :class:`Scene` for the renderer. Every size, count and range comes from
the :class:`~vpr_nb.synthetic.config.WorldConfig`; the constants below are rendering constants
(colours, the skyline's shape, texture phases), pinned by the pixel hashes of ``tests/test_synthetic.py``.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

# segment materials (Scene.kind)
WALL, TREE, POLE, FENCE = 0, 1, 2, 3
DISTRACTOR = 4   # per-visit boxes (vpr_nb.synthetic.distractors): added per camera, never in a world's Scene


def rgb(r: float, g: float, b: float) -> np.ndarray:
    """A read-only colour constant."""
    c = np.array([r, g, b])
    c.flags.writeable = False
    return c


# Facade palette: the base colours the style library cycles through (rgb in [0, 1]).
FACADE_PALETTE = np.array([[0.72, 0.38, 0.28], [0.80, 0.75, 0.62], [0.55, 0.55, 0.58], [0.85, 0.82, 0.78],
                           [0.45, 0.30, 0.22], [0.62, 0.70, 0.75], [0.78, 0.62, 0.40], [0.35, 0.38, 0.45],
                           [0.70, 0.55, 0.55], [0.58, 0.65, 0.50], [0.90, 0.88, 0.70], [0.40, 0.45, 0.40]])
FACADE_PALETTE.flags.writeable = False
MIN_WALL_ALBEDO = 0.05             # a wall's colour channels are clipped to [0.05, 1]
TREE_COLOUR = rgb(0.2, 0.5, 0.15)  # mean tree colour (the renderer varies the foliage around it)
TREE_QUAD_YAW_JITTER = 0.2         # a tree's two quads at 45 and 135 degrees, each turned by up to +-0.2 rad
TREE_STYLES = 4                    # non-wall segments reuse style ids 0..3 (leaf hash variety)
SKYLINE_SAMPLES = 1440             # skyline profile: one height per 0.25 degree ...
SKYLINE_HARMONICS = 23             # ... a sum of 23 cosines with 1/f amplitudes ...
SKYLINE_TOWER = 8                  # ... and, with skyline_blockiness, flat towers 8 samples (2 degrees) wide


class SegmentStore:
    """Segments being laid out, appended in batches, frozen by :func:`finish_scene`."""

    FIELDS = ("a", "b", "z0", "z1", "kind", "style", "colour", "u0")

    def __init__(self):
        self.parts: dict[str, list] = {}

    def add(self, a, b, z0, z1, kind, style, colour, u0) -> None:
        """Append segments from ``a`` to ``b`` (S, 2), from height ``z0`` to ``z1``, of material ``kind``,
        facade ``style``, base ``colour`` (S, 3) and texture offset ``u0`` (m along the segment)."""
        for k, v in zip(self.FIELDS, (a, b, z0, z1, kind, style, colour, u0)):
            self.parts.setdefault(k, []).append(np.asarray(v, dtype=np.float64))


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
    sky_profile: np.ndarray  # (SKYLINE_SAMPLES,) skyline elevation (m at sky_radius) per 0.25 degree
    world: object            # the WorldKind record (its ground texture and skyline colour)
    styles: np.ndarray       # (num_facade_types, 9) facade style table (facade_styles)
    layout: dict             # the kind's plan, read by its cameras and ground texture


def facade_styles(cfg, rng: np.random.Generator) -> np.ndarray:
    """(num_facade_types, 9) facade style table: base rgb, window spacing, floor height, window w/h
    fraction, band flag, shop-floor flag (the renderer's :func:`~vpr_nb.synthetic.render._facade_albedo`
    reads these columns)."""
    n = cfg.num_facade_types
    st = np.empty((n, 9))
    st[:, :3] = FACADE_PALETTE[np.arange(n) % len(FACADE_PALETTE)] + rng.normal(0, cfg.style_colour_variation, (n, 3))
    st[:, 3] = rng.uniform(*cfg.window_spacing, n)
    st[:, 4] = rng.uniform(*cfg.floor_height, n)
    st[:, 5] = rng.uniform(*cfg.window_width, n)
    st[:, 6] = rng.uniform(*cfg.window_height, n)
    st[:, 7] = rng.random(n) < cfg.band_share
    st[:, 8] = rng.random(n) < cfg.shop_share
    return np.clip(st, 0, None)


def skyline(cfg, rng: np.random.Generator) -> np.ndarray:
    """Skyline elevation (metres at the ring radius) sampled every 0.25 degrees around the world: smooth
    hills, mixed with flat-topped towers of random height by ``skyline_blockiness``, scaled to
    ``skyline_height``."""
    n = SKYLINE_SAMPLES
    ang = np.arange(n) * 2 * np.pi / n
    prof = np.zeros(n)
    for f in range(1, SKYLINE_HARMONICS + 1):
        amp = rng.normal(0, 1.0 / f)
        prof += amp * np.cos(f * ang + rng.uniform(0, 2 * np.pi))
    prof = (prof - prof.min()) / (np.ptp(prof) + 1e-9)
    b = cfg.skyline_blockiness
    if b > 0:
        steps = np.repeat(rng.uniform(0, 1, n // SKYLINE_TOWER), SKYLINE_TOWER)
        prof = (1 - b) * prof + b * steps
    lo, hi = cfg.skyline_height
    return lo + (hi - lo) * prof


def tree_segments(store: SegmentStore, pos: np.ndarray, cfg, rng: np.random.Generator) -> None:
    """Trees at ``pos`` (n, 2), each two crossed vertical quads (visible from any side)."""
    n = len(pos)
    r = rng.uniform(*cfg.tree_radius, n)
    h = rng.uniform(*cfg.tree_height, n)
    col = np.clip(TREE_COLOUR + rng.normal(0, cfg.tree_colour_variation, (n, 3)), 0, 1)
    jit = TREE_QUAD_YAW_JITTER
    for ang in (0.25 * np.pi, 0.75 * np.pi):
        d = np.stack([np.cos(ang + rng.uniform(-jit, jit, n)), np.sin(ang + rng.uniform(-jit, jit, n))], 1) * r[:, None]
        store.add(pos - d, pos + d, np.zeros(n), h, np.full(n, TREE), rng.integers(0, TREE_STYLES, n), col, np.zeros(n))


def finish_scene(store: SegmentStore, cfg, rng: np.random.Generator, world, center: np.ndarray, layout: dict,
                 styles: np.ndarray) -> Scene:
    """Freeze the laid-out segments into a :class:`Scene`, with the skyline ring around ``center``."""
    arr = {k: (np.concatenate(v) if v[0].ndim else np.asarray(v)) for k, v in store.parts.items()}
    return Scene(a=arr["a"], b=arr["b"], z0=arr["z0"], z1=arr["z1"], kind=arr["kind"].astype(np.int64),
                 style=arr["style"].astype(np.int64), colour=arr["colour"], u0=arr["u0"],
                 sky_center=center, sky_radius=cfg.sky_radius, sky_profile=skyline(cfg, rng),
                 world=world, styles=styles, layout=layout)
