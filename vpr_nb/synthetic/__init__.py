"""A procedural visual-place-recognition world: the teaching dataset of every notebook.

``make_dataset(preset, seed)`` builds a small geotagged world and renders it with a 2.5-D ray caster
(numpy only, no downloads). Two world kinds (``preset``) mirror the two kinds of real benchmark:

``"city"`` (Pittsburgh-like)
    a street grid lined with buildings; database images every ``place_spacing`` metres along every
    street, in ``headings`` directions per place, all in the reference condition; queries at random
    street positions with viewpoint jitter and another condition. Positives: within 25 m.
``"route"`` (Nordland-like)
    one long railway through countryside (trees, houses, poles, fences, hills); a camera looking
    forward takes one frame every ``frame_spacing`` metres; the database is summer, the queries
    winter, frame-aligned. Positives: the same frame +-1 (``pos_radius = 1.01 * frame_spacing``).
    ``camera_spacing=1.0`` (route density) takes frames 1 m apart along the same track, the query jitters
    scaled to the spacing (:mod:`~vpr_nb.synthetic.kinds.route`).

What makes it VPR-shaped (and what the knobs of :class:`WorldConfig` control):

* **parallax layers** - a far skyline ring (almost no parallax), near facades / trees (strong parallax)
  and a textured ground plane, so nearby cameras share content and the view changes continuously
  with distance;
* **perceptual aliasing** - facades are drawn from a small library of ``num_facade_types`` styles, so
  distant places can look alike (``colour_variation`` sets how much individual buildings differ);
* **condition changes** - illumination and sun direction, season palettes (foliage, snow), fog,
  rain noise, lit windows at dusk (``condition_strength`` scales them all);
* **occluders** - passing cars and pedestrians drawn into query images (``occluder_rate``);
* **distractors** - parked cars and pedestrians in 3-D, new at every visit, in database and query images
  alike (``distractor_rate``, off by default: :mod:`~vpr_nb.synthetic.distractors`);
* **camera jitter** - position, heading and pitch noise of the query cameras.

Splits (train / val / test) are geographically disjoint bands separated by a gap wider than the
positive radius, so no query has a positive in another split.

Modules: :mod:`~vpr_nb.synthetic.config` (:class:`WorldConfig`, :func:`make_config`: every scene knob),
:mod:`~vpr_nb.synthetic.kinds` (one record per world kind: its layout, cameras, ground texture and
defaults), :mod:`~vpr_nb.synthetic.layout` (the scene's segments and their building blocks),
:mod:`~vpr_nb.synthetic.cameras` (camera sets, split bands), :mod:`~vpr_nb.synthetic.conditions`
(the condition table), :mod:`~vpr_nb.synthetic.render` (the ray caster), :mod:`~vpr_nb.synthetic.labels`
(:data:`LABEL_NAMES`: what each pixel shows, ``make_dataset(..., labels=True)``),
:mod:`~vpr_nb.synthetic.distractors` (per-visit boxes),
:mod:`~vpr_nb.synthetic.dataset` (:class:`VPRDataset`) and :mod:`~vpr_nb.synthetic.world`
(:func:`make_dataset`).
"""
from __future__ import annotations

from .conditions import CONDITIONS
from .config import SPLITS, WorldConfig, make_config
from .dataset import VPRDataset
from .kinds import WORLD_KINDS, WorldKind, world_kind
from .labels import LABEL_NAMES
from .layout import FENCE, POLE, TREE, WALL, Scene
from .world import make_dataset

__all__ = ["CONDITIONS", "SPLITS", "WorldConfig", "make_config", "VPRDataset", "WORLD_KINDS", "WorldKind",
           "world_kind", "Scene", "WALL", "TREE", "POLE", "FENCE", "make_dataset", "LABEL_NAMES"]
